"""The ComfyUI nodes' functions on a batch of two images (numpy stands in for torch tensors; the
conversion is the same): shapes kept, each image relit as pixlrelight.relight relights it alone,
a batch-1 depth serving both, the intrinsics at the working size."""
import importlib.util
import sys
from pathlib import Path

import numpy as np

import pixlrelight

HERE = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("pixl_comfy", HERE / "__init__.py", submodule_search_locations=[str(HERE)])
pixl_comfy = importlib.util.module_from_spec(spec)
sys.modules["pixl_comfy"] = pixl_comfy
spec.loader.exec_module(pixl_comfy)


def batch():
    h, w = 32, 48
    y, x = np.mgrid[0:h, 0:w]
    a = np.stack([0.2 + 0.5 * x / w, 0.3 + 0.2 * y / h, 0.4 + 0.1 * ((x // 4 + y // 4) % 2)], -1)
    return np.stack([a, a[:, ::-1] * 0.8]).astype(np.float32)


def test_nodes_are_registered():
    assert set(pixl_comfy.NODE_CLASS_MAPPINGS) == {"PixlRelight", "PixlEstimateDepth", "PixlIntrinsics"}
    for cls in pixl_comfy.NODE_CLASS_MAPPINGS.values():
        assert "required" in cls.INPUT_TYPES() and hasattr(cls, cls.FUNCTION)


def test_relight_a_batch_of_two():
    images = batch()
    depth = np.full((1, 32, 48), 3.0, dtype=np.float32)
    node = pixl_comfy.NODE_CLASS_MAPPINGS["PixlRelight"]()
    (out,) = node.relight(images, "cool-side-flash", "--type point --from left --power 50", "bundled", 64, 2, 0,
                          depth=depth)
    assert out.shape == images.shape and out.dtype == np.float32
    for i in range(2):
        alone = pixlrelight.relight(images[i], preset="cool-side-flash", lights=["--type point --from left --power 50"],
                                    depth=depth[0], max_side=64, spp=2)
        assert np.array_equal(out[i], alone)
    assert not np.array_equal(out[0], out[1])


def test_intrinsics_of_a_batch_of_two():
    images = batch()
    depth = np.full((2, 32, 48), 2.5, dtype=np.float32)
    node = pixl_comfy.NODE_CLASS_MAPPINGS["PixlIntrinsics"]()
    albedo, shading, residual = node.intrinsics(images, depth, "warm-overhead-flash", "", 24, 2)
    for m in (albedo, shading, residual):
        assert m.shape == (2, 16, 24, 3)
    assert shading.max() > 0
