#!/usr/bin/env python3
"""A randomly initialised Marigold checkpoint (IID or normals) at the REAL model sizes, for CPU benchmarks.

    usage: marigold_random_checkpoint.py {appearance,lighting,normals} OUT_DIR [--seed N]

Writes OUT_DIR in the diffusers layout that `pixl` and diffusers' `MarigoldIntrinsicsPipeline` (or
`MarigoldNormalsPipeline`) both read (model_index.json, scheduler/, unet/, vae/, text_encoder/,
tokenizer/), with the weights as the `.fp16` variant only (`*.fp16.safetensors`, what pixl's registry downloads; both loaders upcast them
to f32). About 2.6 GB per folder. The outputs are meaningless: this is for timing and memory only.

Architectures (Stable Diffusion 2, as the released prs-eth/marigold-iid-*-v1-1 and prs-eth/marigold-normals-v1-1
checkpoints):
  - UNet2DConditionModel: block_out_channels (320, 640, 1280, 1280), attention_head_dim (5, 10, 20, 20),
    cross_attention_dim 1024, use_linear_projection, layers_per_block 2, 32 groups, sample_size 96;
    in/out channels 12/8 (appearance: 2 targets), 16/12 (lighting: 3 targets) or 8/4 (normals: 1 target).
    ~0.87 B parameters.
  - AutoencoderKL: block_out_channels (128, 256, 512, 512), layers_per_block 2, 4 latent channels,
    scaling_factor 0.18215. ~84 M parameters.
  - CLIPTextModel: hidden 1024, 23 layers, 16 heads, intermediate 4096, gelu, vocab 49408, 77 positions.
    ~0.34 B parameters.
Weights: the libraries' own default initialisation (PyTorch's for the diffusers models, transformers'
`_init_weights` for CLIP), drawn from a fixed seed. Before saving, one UNet forward and one text
encoder forward are run on the fp16-rounded weights and must be finite.

model_index.json, the scheduler config and the tokenizer are those of the test fixtures
(fixtures/marigold/{appearance,lighting,normals}/): the tokenizer's vocabulary is tiny but holds
<|startoftext|> and <|endoftext|>, the only tokens of Marigold's empty prompt; the text encoder's
config uses their ids as bos/eos.

Needs the reference venv of scripts/fixtures/marigold.py (torch 2.15, diffusers 0.42.1,
transformers 5.24). Not run by CI; used by scripts/bench-marigold.sh. Nothing is downloaded.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import torch  # noqa: E402
from safetensors.torch import load_file, save_file  # noqa: E402
from transformers import CLIPTextConfig, CLIPTextModel  # noqa: E402

from diffusers import AutoencoderKL, UNet2DConditionModel  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
FIXTURES = ROOT / "fixtures" / "marigold"
N_TARGETS = {"appearance": 2, "lighting": 3, "normals": 1}

UNET = dict(
    sample_size=96,
    down_block_types=("CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"),
    up_block_types=("UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"),
    block_out_channels=(320, 640, 1280, 1280),
    layers_per_block=2,
    attention_head_dim=(5, 10, 20, 20),
    cross_attention_dim=1024,
    use_linear_projection=True,
    norm_num_groups=32,
    norm_eps=1e-5,
    flip_sin_to_cos=True,
    freq_shift=0,
    act_fn="silu",
    downsample_padding=1,
    center_input_sample=False,
    upcast_attention=False,
)
VAE = dict(
    in_channels=3,
    out_channels=3,
    down_block_types=["DownEncoderBlock2D"] * 4,
    up_block_types=["UpDecoderBlock2D"] * 4,
    block_out_channels=[128, 256, 512, 512],
    layers_per_block=2,
    act_fn="silu",
    latent_channels=4,
    norm_num_groups=32,
    sample_size=768,
    scaling_factor=0.18215,
)
TEXT = dict(
    vocab_size=49408,
    hidden_size=1024,
    intermediate_size=4096,
    projection_dim=512,
    num_hidden_layers=23,
    num_attention_heads=16,
    max_position_embeddings=77,
    hidden_act="gelu",
    layer_norm_eps=1e-5,
    pad_token_id=0,
)


def n_params(m: torch.nn.Module) -> int:
    return sum(p.numel() for p in m.parameters())


def check_finite(name: str, t: torch.Tensor) -> None:
    ok = bool(torch.isfinite(t).all())
    print(f"  {name}: shape {tuple(t.shape)}, std {t.float().std():.4g}, max |x| {t.abs().max():.4g}, finite {ok}",
          flush=True)
    if not ok:
        raise SystemExit(f"{name}: non-finite output with these random weights")


def save_fp16(sd: dict[str, torch.Tensor], path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    save_file({k: v.detach().to(torch.float16).contiguous() for k, v in sd.items()}, str(path),
              metadata={"format": "pt"})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kind", choices=sorted(N_TARGETS))
    ap.add_argument("out", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    src = FIXTURES / args.kind
    out: Path = args.out
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    t0 = time.time()

    # Configs and tokenizer from the fixture folder.
    shutil.copy(src / "model_index.json", out / "model_index.json")
    shutil.copytree(src / "scheduler", out / "scheduler")
    shutil.copytree(src / "tokenizer", out / "tokenizer")
    vocab = json.loads((src / "tokenizer" / "vocab.json").read_text())
    bos, eos = vocab["<|startoftext|>"], vocab["<|endoftext|>"]
    assert max(bos, eos) < TEXT["vocab_size"]

    # Text encoder.
    torch.manual_seed(args.seed)
    text = CLIPTextModel(CLIPTextConfig(**TEXT, bos_token_id=bos, eos_token_id=eos)).eval()
    text.half().float()  # round to f16 as stored
    print(f"text encoder: {n_params(text) / 1e6:.1f} M parameters", flush=True)
    with torch.no_grad():
        emb = text(torch.tensor([[bos, eos]]))[0]
    check_finite("text encoder last_hidden_state", emb)
    text.save_pretrained(str(out / "text_encoder"), safe_serialization=True)
    # transformers 5 saves without the `text_model.` prefix; diffusers' and pixl's loaders (and the
    # released checkpoints) use `text_model.*` (as scripts/fixtures/marigold.py does).
    for f in (out / "text_encoder").glob("model*.safetensors"):
        f.unlink()
    sd = text.state_dict()
    sd = {(k if k.startswith("text_model.") else "text_model." + k): v for k, v in sd.items()}
    save_fp16(sd, out / "text_encoder" / "model.fp16.safetensors")
    del text, sd

    # VAE.
    torch.manual_seed(args.seed + 1)
    vae = AutoencoderKL(**VAE).eval()
    vae.half().float()
    print(f"vae: {n_params(vae) / 1e6:.1f} M parameters", flush=True)
    vae.save_config(str(out / "vae"))
    save_fp16(vae.state_dict(), out / "vae" / "diffusion_pytorch_model.fp16.safetensors")
    del vae

    # UNet.
    t = N_TARGETS[args.kind]
    torch.manual_seed(args.seed + 2)
    unet = UNet2DConditionModel(in_channels=4 * (t + 1), out_channels=4 * t, **UNET).eval()
    unet.half().float()
    print(f"unet: {n_params(unet) / 1e6:.1f} M parameters (in {4 * (t + 1)}, out {4 * t})", flush=True)
    with torch.no_grad():
        x = torch.randn(1, 4 * (t + 1), 32, 32, generator=torch.Generator().manual_seed(1))
        y = unet(x, torch.tensor([999]), encoder_hidden_states=emb).sample
    check_finite("unet output (32x32 latent, t=999)", y)
    unet.save_config(str(out / "unet"))
    save_fp16(unet.state_dict(), out / "unet" / "diffusion_pytorch_model.fp16.safetensors")
    del unet

    # Sanity: every stored weight file is f16.
    for f in sorted(out.rglob("*.safetensors")):
        dts = {v.dtype for v in load_file(str(f)).values()}
        assert dts == {torch.float16}, (f, dts)
        print(f"  {f.relative_to(out)}: {f.stat().st_size / 1e9:.3f} GB", flush=True)
    print(f"wrote {out} in {time.time() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
