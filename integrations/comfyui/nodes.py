"""The node classes (see __init__.py). Each node's FUNCTION works on numpy arrays as well as on
torch tensors, so it can be tested without ComfyUI or torch."""
import numpy as np

import pixlrelight

try:  # ComfyUI passes torch tensors and expects them back.
    import torch
except ImportError:  # pragma: no cover - outside ComfyUI
    torch = None

_MODELS = {}


def _model(weights):
    if weights not in _MODELS:
        _MODELS[weights] = pixlrelight.Model.load(weights)
    return _MODELS[weights]


def _frames(batch):
    """A [B, H, W, C] image (tensor or array) as a list of float32 H x W x 3 arrays."""
    a = batch.detach().cpu().numpy() if hasattr(batch, "detach") else np.asarray(batch)
    if a.ndim == 3:
        a = a[None]
    if a.ndim != 4 or a.shape[-1] < 3:
        raise ValueError(f"expected an IMAGE of shape [B, H, W, 3], got {a.shape}")
    return [np.ascontiguousarray(np.clip(f[..., :3], 0.0, 1.0), dtype=np.float32) for f in a]


def _pick(items, i):
    return items[i] if len(items) > 1 else items[0]


def _batch(frames, like):
    out = np.stack(frames).astype(np.float32)
    if torch is not None and hasattr(like, "detach"):
        return torch.from_numpy(out)
    return out


def _masks(maps, like):
    out = np.stack(maps).astype(np.float32)
    if torch is not None and hasattr(like, "detach"):
        return torch.from_numpy(out)
    return out


LIGHT_HELP = "one light per line, the flags of `pixl light add` (e.g. --type spot --from left --power 300)"


class PixlRelight:
    """Image + preset/lights (with a depth map, or Depth Anything 3 from disk) or a reference
    image → the relit image, at the image's size."""

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                "image": ("IMAGE",),
                "preset": (["none"] + pixlrelight.presets(), {"default": "warm-overhead-flash"}),
                "lights": ("STRING", {"multiline": True, "default": "", "tooltip": LIGHT_HELP}),
                "weights": (["bundled", "pixlrelight"], {"default": "bundled"}),
                "max_side": ("INT", {"default": 1024, "min": 64, "max": 4096, "step": 64}),
                "spp": ("INT", {"default": 64, "min": 1, "max": 4096}),
                "seed": ("INT", {"default": 0, "min": 0, "max": 2**31 - 1}),
            },
            "optional": {"depth": ("MASK",), "reference": ("IMAGE",)},
        }

    RETURN_TYPES = ("IMAGE",)
    FUNCTION = "relight"
    CATEGORY = "image/relighting"

    def relight(self, image, preset, lights, weights, max_side, spp, seed, depth=None, reference=None):
        frames = _frames(image)
        words = [w.strip() for w in lights.splitlines() if w.strip()]
        refs = _frames(reference) if reference is not None else None
        depths = None
        if depth is not None:
            d = depth.detach().cpu().numpy() if hasattr(depth, "detach") else np.asarray(depth)
            depths = [np.asarray(x, dtype=np.float32) for x in (d if d.ndim == 3 else d[None])]
        model = _model(weights)
        out = []
        for i, f in enumerate(frames):
            kwargs = dict(model=model, max_side=max_side, spp=spp, seed=seed)
            if refs is not None:
                kwargs["like"] = _pick(refs, i)
            else:
                kwargs["preset"] = None if preset == "none" else preset
                kwargs["lights"] = words
                if depths is not None:
                    kwargs["depth"] = _pick(depths, i)
            out.append(pixlrelight.relight(f, **kwargs))
        return (_batch(out, image),)


class PixlEstimateDepth:
    """Image → metric depth in metres (a MASK of the image's size; 0 = sky), with Depth Anything 3
    (metric) from disk (`pixl models fetch da3-metric`)."""

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {"image": ("IMAGE",), "fov": ("FLOAT", {"default": 50.0, "min": 1.0, "max": 179.0})}}

    RETURN_TYPES = ("MASK",)
    FUNCTION = "estimate"
    CATEGORY = "image/relighting"

    def estimate(self, image, fov):
        return (_masks([pixlrelight.estimate_depth(f, fov=fov) for f in _frames(image)], image),)


class PixlIntrinsics:
    """Image + depth + preset/lights → the target intrinsics C_T the network is conditioned on:
    albedo, diffuse shading and non-diffuse residual, path-traced at the working size."""

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                "image": ("IMAGE",),
                "depth": ("MASK",),
                "preset": (["none"] + pixlrelight.presets(), {"default": "warm-overhead-flash"}),
                "lights": ("STRING", {"multiline": True, "default": "", "tooltip": LIGHT_HELP}),
                "max_side": ("INT", {"default": 512, "min": 16, "max": 4096}),
                "spp": ("INT", {"default": 64, "min": 1, "max": 4096}),
            }
        }

    RETURN_TYPES = ("IMAGE", "IMAGE", "IMAGE")
    RETURN_NAMES = ("albedo", "shading", "residual")
    FUNCTION = "intrinsics"
    CATEGORY = "image/relighting"

    def intrinsics(self, image, depth, preset, lights, max_side, spp):
        words = [w.strip() for w in lights.splitlines() if w.strip()]
        d = depth.detach().cpu().numpy() if hasattr(depth, "detach") else np.asarray(depth)
        depths = [np.asarray(x, dtype=np.float32) for x in (d if d.ndim == 3 else d[None])]
        maps = {"albedo": [], "shading": [], "residual": []}
        for i, f in enumerate(_frames(image)):
            ct = pixlrelight.intrinsics(f, _pick(depths, i), preset=None if preset == "none" else preset,
                                        lights=words, max_side=max_side, spp=spp)
            for k in maps:
                maps[k].append(np.clip(ct[k], 0.0, 1.0))
        return tuple(_batch(maps[k], image) for k in ("albedo", "shading", "residual"))


NODE_CLASS_MAPPINGS = {
    "PixlRelight": PixlRelight,
    "PixlEstimateDepth": PixlEstimateDepth,
    "PixlIntrinsics": PixlIntrinsics,
}
NODE_DISPLAY_NAME_MAPPINGS = {
    "PixlRelight": "PIXL Relight",
    "PixlEstimateDepth": "PIXL Estimate Depth",
    "PixlIntrinsics": "PIXL Intrinsics",
}
