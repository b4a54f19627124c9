"""ComfyUI nodes for pixlrelight: relight an image under new lights or like a reference image,
estimate its depth, and show the intrinsics (C_T) the network is conditioned on.

Install: copy this folder into ComfyUI/custom_nodes/ and `pip install` the pixlrelight wheel into
ComfyUI's Python. Images follow ComfyUI's convention: IMAGE is a [B, H, W, C] float tensor in
[0, 1]; every node handles a batch image by image (a reference image or a depth map of batch 1
serves every image of the batch). The network is loaded once per weights choice and kept.
"""
from .nodes import NODE_CLASS_MAPPINGS, NODE_DISPLAY_NAME_MAPPINGS

__all__ = ["NODE_CLASS_MAPPINGS", "NODE_DISPLAY_NAME_MAPPINGS"]
