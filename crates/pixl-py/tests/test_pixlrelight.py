"""pixlrelight from Python, against the `pixl` binary: the same photo, depth, weights and lights
give the same relit image bit for bit; bad input raises a clear exception; one loaded model serves
many calls without loading again.

Needs: the built wheel installed, numpy, pytest, and the `pixl` binary (PIXL_BIN, default
target/debug/pixl from `cargo build`); PIL for the PIL test (skipped without it).
"""
import os
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

import pixlrelight

ROOT = Path(__file__).resolve().parents[3]
PIXL = os.environ.get("PIXL_BIN", str(ROOT / "target" / "debug" / "pixl"))


def pixl(*args):
    env = dict(os.environ, PIXL_MODELS_DIR="/nonexistent", HF_HOME="/nonexistent")
    out = subprocess.run([PIXL, *map(str, args), "--quiet"], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    return out


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The demo scene rendered at 96x64: a photo (8-bit PNG) and its depth (the EXR's Depth pass)."""
    d = tmp_path_factory.mktemp("demo")
    pixl("render", ROOT / "assets/demo/scene.toml", "--spp", "4", "--size", "96x64",
         "-o", d / "in.exr", "--preview", d / "photo.png")
    return d


def read_png8(path):
    """An 8-bit PNG as uint8 H x W x 3 (through pixlrelight's reader: values are v / 255)."""
    return np.round(pixlrelight.read_image(str(path)) * 255).astype(np.uint8)


def test_version():
    assert isinstance(pixlrelight.__version__, str) and pixlrelight.__version__.count(".") == 2
    assert "warm-overhead-flash" in pixlrelight.presets()


def test_relight_equals_the_cli_bit_for_bit(demo, tmp_path):
    photo = read_png8(demo / "photo.png")
    model = pixlrelight.Model.load("bundled")
    ours = pixlrelight.relight(photo, preset="warm-overhead-flash", depth=str(demo / "in.exr"), model=model,
                               spp=8, lights=["--type point --at-pixel 40,20 --power 30"])
    assert ours.dtype == np.float32 and ours.shape == (64, 96, 3)
    # The CLI's 32-bit float output, read back exactly.
    out = tmp_path / "cli.exr"
    pixl("relight", demo / "photo.png", "--depth", demo / "in.exr", "--preset", "warm-overhead-flash",
         "--light", "--type point --at-pixel 40,20 --power 30", "--spp", "8", "--weights", "bundled", "-o", out)
    cli = pixlrelight.read_image(str(out))
    assert cli.shape == ours.shape
    assert np.array_equal(cli, ours), f"max difference {np.abs(cli - ours).max()}"
    # And a different light gives a different image.
    other = pixlrelight.relight(photo, preset="cool-side-flash", depth=str(demo / "in.exr"), model=model, spp=8)
    assert np.abs(other - ours).mean() > 1e-3


def test_one_model_serves_many_calls(demo):
    photo = read_png8(demo / "photo.png")
    depth = np.full((64, 96), 3.0, dtype=np.float32)
    model = pixlrelight.Model.load("bundled")
    before = pixlrelight.Model.loads()
    seen = []
    t = time.time()
    for i in range(8):
        pixlrelight.relight(photo, preset="cool-side-flash", depth=depth, model=model, spp=2, max_side=48,
                            progress=lambda stage, done, total: seen.append(stage))
    assert pixlrelight.Model.loads() == before, "no call loaded the network again"
    assert "network" in seen and "rendering" in seen
    assert time.time() - t < 120


def test_bad_inputs_raise_clear_exceptions(demo):
    photo = read_png8(demo / "photo.png")
    depth = np.full((64, 96), 3.0, dtype=np.float32)
    with pytest.raises(TypeError, match="dtype int64"):
        pixlrelight.relight(photo.astype(np.int64), preset="cool-side-flash", depth=depth)
    with pytest.raises(ValueError, match="H x W x 3"):
        pixlrelight.relight(photo[:, :, :2], preset="cool-side-flash", depth=depth)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        pixlrelight.relight(photo.astype(np.float32), preset="cool-side-flash", depth=depth)
    with pytest.raises(ValueError, match="depth"):
        pixlrelight.relight(photo, preset="cool-side-flash", depth=depth[:10])
    with pytest.raises(ValueError, match="moonlight"):
        pixlrelight.relight(photo, preset="moonlight", depth=depth)
    with pytest.raises(ValueError, match="give the new lighting"):
        pixlrelight.relight(photo, depth=depth)
    with pytest.raises(FileNotFoundError, match="no such file"):
        pixlrelight.Model.load("missing.safetensors")
    with pytest.raises(FileNotFoundError, match="pixl models fetch da3-metric"):
        pixlrelight.relight(photo, preset="cool-side-flash", models_dir="/nonexistent")


def test_pil_images_and_intrinsics(demo):
    PIL = pytest.importorskip("PIL.Image")
    photo = read_png8(demo / "photo.png")
    img = PIL.fromarray(photo)
    depth = str(demo / "in.exr")
    a = pixlrelight.relight(img, preset="cool-side-flash", depth=depth, spp=2)
    b = pixlrelight.relight(photo, preset="cool-side-flash", depth=depth, spp=2)
    assert np.array_equal(a, b)
    ct = pixlrelight.intrinsics(photo, depth, preset="cool-side-flash", max_side=48, spp=2)
    assert set(ct) == {"albedo", "shading", "residual"}
    assert ct["shading"].shape == (32, 48, 3) and ct["shading"].max() > 0
