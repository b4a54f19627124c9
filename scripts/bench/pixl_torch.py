#!/usr/bin/env python3
"""PIXLRelight in PyTorch: an independent implementation of the `pixl-model` network, for parity
checks, speed comparisons and gradient checks against `pixl` (scripts/bench-vs-pytorch.sh,
scripts/bench-train-vs-pytorch.sh, scripts/check-train-grads.sh).

It loads a `pixl` checkpoint (safetensors, config JSON in the `config` metadata, tensor names as in
crates/pixl-model/README.md) with `load_state_dict(strict=True)`: the module tree below has
exactly the checkpoint's names. Classes mirror the Rust modules: `VitEncoder` (vit.rs),
`ConvNextEncoder` (convnext.rs), `Fusion` (fusion.rs), `Trunk` (trunk.rs, with `Rope2d` from
pixl-nn rope.rs), `DptHead` (dpt.rs), `Modulation` (modulation.rs), `PixlRelight` (model.rs), and
`relight_full` for the working-resolution path of fullres.rs (what `pixl relight` runs).

Commands (f32 on the CPU unless said otherwise):

  run      --weights W --source S --intrinsics CT --out O [--max-side N]
           the network on a source (.exr/.png/.npy, RGB in [0, 1]) and a C_T (.exr with
           albedo.R/G/B, shading.*, residual.*; or a (9, H, W) .npy), output .exr or .npy (3, H, W).
  parity   the same inputs plus --reference REF (a `pixl relight` output): prints the max and mean
           absolute difference and exits 1 above --tol (default 1e-4).
  time     --weights W | --config PRESET, --size WxH: `pixl bench model`'s protocol (warm-ups,
           then timed runs, uniform random inputs), --threads N; prints median/min ms and peak RSS.
  perturb  --weights IN --out OUT --seed S: adds seeded noise to every tensor so that every part of
           the network (also the zero-initialised modulation conv) affects the output.
  inputs   --size WxH --seed S --source S.exr --intrinsics CT.exr: random source and C_T files.
  train-step  --weights W | --config PRESET, --size WxH, --batch B: `pixl bench train-step`'s
           step (forward, L1 loss on the clipped output, backward, global-norm clip at 1,
           AdamW lr 1e-4 with pixl's betas, eps and decay groups), its protocol (warm-ups, timed
           runs, uniform random inputs), --threads N; prints per-step times, the median, the
           median forward / backward / clip+AdamW split, peak RSS (scripts/bench-train-vs-pytorch.sh).
  grads    --weights W --inputs I --out G [--dtype f64]: the same loss on `src`, `ct`, `tgt` from
           the safetensors file I, and every parameter's gradient, computed in float64, saved
           under the checkpoint's names (scripts/check-train-grads.sh).
  compare-grads A B --tol X: per-tensor relative L2 error ‖a − b‖₂ / ‖b‖₂, worst first; exits 1
           if any tensor is above X, missing or misshapen.

Requirements: torch, safetensors, numpy; OpenEXR (pip `openexr`) for .exr files; Pillow for .png.
"""
from __future__ import annotations

import argparse
import json
import math
import resource
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

# ---------------------------------------------------------------------------------------------
# Configuration (config.rs)
# ---------------------------------------------------------------------------------------------


def spread_readouts(depth: int) -> list[int]:
    """Readouts spread over `depth` blocks as {4, 11, 17, 23} are over 24 (config.rs)."""
    out: list[int] = []
    for f in (5.0, 12.0, 18.0, 24.0):
        # Rust's f64::round rounds half away from zero; Python's round() rounds half to even.
        r = max(int(math.floor(f / 24.0 * depth + 0.5)), 1) - 1
        out.append(max(r, out[-1] + 1) if out else r)
    return out


def preset(name: str) -> dict:
    """The `tiny`, `small` and `paper` presets, in the checkpoint metadata's JSON form."""
    if name == "paper":
        return {
            "dim": 1024, "norm_eps": 1e-6,
            "src_encoder": {"depth": 24, "heads": 16, "mlp_ratio": 4, "pos_grid": 32},
            "cond_encoder": {"dims": [128, 256, 512, 1024], "depths": [3, 3, 27, 3], "layer_scale_init": 1e-6},
            "trunk": {"depth": 24, "heads": 16, "mlp_ratio": 4, "registers": 8, "rope_base": 100.0,
                      "readouts": [4, 11, 17, 23]},
            "head": {"out_channels": [256, 512, 1024, 1024], "features": 256, "hidden": 32},
        }
    if name == "small":
        return {
            "dim": 384, "norm_eps": 1e-6,
            "src_encoder": {"depth": 6, "heads": 6, "mlp_ratio": 4, "pos_grid": 32},
            "cond_encoder": {"dims": [48, 96, 192, 384], "depths": [1, 1, 3, 1], "layer_scale_init": 1e-6},
            "trunk": {"depth": 8, "heads": 6, "mlp_ratio": 4, "registers": 4, "rope_base": 100.0,
                      "readouts": spread_readouts(8)},
            "head": {"out_channels": [48, 96, 192, 384], "features": 128, "hidden": 32},
        }
    if name == "tiny":
        return {
            "dim": 64, "norm_eps": 1e-6,
            "src_encoder": {"depth": 2, "heads": 2, "mlp_ratio": 4, "pos_grid": 16},
            "cond_encoder": {"dims": [16, 32, 64, 64], "depths": [1, 1, 1, 1], "layer_scale_init": 0.1},
            "trunk": {"depth": 4, "heads": 2, "mlp_ratio": 4, "registers": 4, "rope_base": 100.0,
                      "readouts": spread_readouts(4)},
            "head": {"out_channels": [16, 32, 64, 64], "features": 32, "hidden": 16},
        }
    raise ValueError(f"unknown preset {name!r} (expected tiny, small or paper)")


def validate(cfg: dict) -> dict:
    """Fills the default patch size (16, absent from older files) and checks what the layers need."""
    cfg = dict(cfg)
    cfg.setdefault("patch", 16)
    if cfg["patch"] not in (4, 8, 16, 32):
        raise ValueError(f"patch {cfg['patch']} must be one of 4, 8, 16, 32")
    t = cfg["trunk"]
    if cfg["dim"] % t["heads"] or (cfg["dim"] // t["heads"]) % 4:
        raise ValueError("trunk head dimension must be an integer divisible by 4 (2D RoPE)")
    if t["readouts"][-1] != t["depth"] - 1:
        raise ValueError("the last readout must be the last trunk block")
    return cfg


def cond_downsamples(cfg: dict, s: int) -> bool:
    """Whether ConvNeXt transition `s` halves the resolution (stride stays ≤ patch)."""
    return (4 << s) <= cfg["patch"]


# ---------------------------------------------------------------------------------------------
# Layers (pixl-nn)
# ---------------------------------------------------------------------------------------------


class Mlp(nn.Module):
    """`fc1 – GELU (exact erf) – fc2` (pixl-nn mlp.rs)."""

    def __init__(self, dim_in: int, hidden: int, dim_out: int):
        super().__init__()
        self.fc1 = nn.Linear(dim_in, hidden)
        self.fc2 = nn.Linear(hidden, dim_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class LayerNorm2d(nn.LayerNorm):
    """LayerNorm over the channels of `(B, C, H, W)` (ConvNeXt's channels-first norm, norm.rs)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return super().forward(x.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)


class Rope2d:
    """2D RoPE tables (pixl-nn rope.rs): the head dimension `D` is split in two halves, the first
    rotated by the token's row, the second by its column; within a half, pairs `(i, i + D/4)`
    rotate by `pos · base^(-i / (D/4))` (rotate-half). Tables computed in f64, stored as `dtype`
    (f32 as pixl's; f64 for the float64 gradient reference)."""

    def __init__(self, head_dim: int, gh: int, gw: int, base: float, dtype: torch.dtype = torch.float32):
        q = head_dim // 4
        freqs = base ** (-torch.arange(q, dtype=torch.float64) / q)  # (q)
        ys, xs = torch.meshgrid(torch.arange(gh, dtype=torch.float64),
                                torch.arange(gw, dtype=torch.float64), indexing="ij")
        ang_y = ys.reshape(-1, 1) * freqs  # (N, q)
        ang_x = xs.reshape(-1, 1) * freqs
        ang = torch.cat([ang_y, ang_y, ang_x, ang_x], dim=1)  # (N, D)
        self.cos = ang.cos().to(dtype)
        self.sin = ang.sin().to(dtype)

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        """Rotates `(B, H, N, D)` queries or keys."""
        a1, a2, b1, b2 = x.chunk(4, dim=-1)
        rot = torch.cat([-a2, a1, -b2, b1], dim=-1)
        return x * self.cos + rot * self.sin


# ---------------------------------------------------------------------------------------------
# Source encoder (vit.rs) — Attention and Block are shared with the trunk
# ---------------------------------------------------------------------------------------------


class Attention(nn.Module):
    """Multi-head self-attention, fused `qkv` (rows q, k, v; heads contiguous) then `proj`."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, rope: Rope2d | None = None, prefix: int = 0) -> torch.Tensor:
        b, n, c = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0], qkv[1], qkv[2]
        if rope is not None:
            # The first `prefix` tokens (registers) keep no position and are not rotated.
            q = torch.cat([q[:, :, :prefix], rope.apply(q[:, :, prefix:])], dim=2)
            k = torch.cat([k[:, :, :prefix], rope.apply(k[:, :, prefix:])], dim=2)
        out = F.scaled_dot_product_attention(q, k, v)  # softmax(q kᵀ / √D) v
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


class Block(nn.Module):
    """Pre-norm transformer block: `x + attn(norm1(x))`, then `x + mlp(norm2(x))`."""

    def __init__(self, dim: int, heads: int, mlp_ratio: int, eps: float):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=eps)
        self.attn = Attention(dim, heads)
        self.norm2 = nn.LayerNorm(dim, eps=eps)
        self.mlp = Mlp(dim, mlp_ratio * dim, dim)

    def forward(self, x: torch.Tensor, rope: Rope2d | None = None, prefix: int = 0) -> torch.Tensor:
        x = x + self.attn(self.norm1(x), rope, prefix)
        return x + self.mlp(self.norm2(x))


class PatchEmbed(nn.Module):
    def __init__(self, dim: int, patch: int):
        super().__init__()
        self.proj = nn.Conv2d(3, dim, patch, stride=patch)


class VitEncoder(nn.Module):
    """ViT over `I_S`, no class token; the learned `pos_grid²` position embedding is resized
    bilinearly (`align_corners=False`) to the image's grid. `(B, 3, H, W)` → `(B, N, d)`."""

    def __init__(self, cfg: dict):
        super().__init__()
        v, d = cfg["src_encoder"], cfg["dim"]
        self.pos_grid = v["pos_grid"]
        self.patch_embed = PatchEmbed(d, cfg["patch"])
        self.pos_embed = nn.Parameter(torch.zeros(1, self.pos_grid ** 2, d))
        self.blocks = nn.ModuleList(Block(d, v["heads"], v["mlp_ratio"], cfg["norm_eps"]) for _ in range(v["depth"]))
        self.norm = nn.LayerNorm(d, eps=cfg["norm_eps"])

    def pos_embed_for(self, gh: int, gw: int) -> torch.Tensor:
        g = self.pos_grid
        if (gh, gw) == (g, g):
            return self.pos_embed
        grid = self.pos_embed.reshape(1, g, g, -1).permute(0, 3, 1, 2)
        grid = F.interpolate(grid, size=(gh, gw), mode="bilinear", align_corners=False)
        return grid.flatten(2).transpose(1, 2)

    def forward(self, src: torch.Tensor) -> torch.Tensor:
        x = self.patch_embed.proj(src)  # (B, d, gh, gw)
        gh, gw = x.shape[-2:]
        x = x.flatten(2).transpose(1, 2) + self.pos_embed_for(gh, gw)
        for block in self.blocks:
            x = block(x)
        return self.norm(x)


# ---------------------------------------------------------------------------------------------
# Intrinsics encoder (convnext.rs)
# ---------------------------------------------------------------------------------------------


class ConvNextBlock(nn.Module):
    """`x + gamma ⊙ mlp(norm(dwconv7(x)))`, channels-last inside."""

    def __init__(self, dim: int, eps: float):
        super().__init__()
        self.conv_dw = nn.Conv2d(dim, dim, 7, padding=3, groups=dim)
        self.norm = nn.LayerNorm(dim, eps=eps)
        self.mlp = Mlp(dim, 4 * dim, dim)
        self.gamma = nn.Parameter(torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.conv_dw(x).permute(0, 2, 3, 1)
        y = self.mlp(self.norm(y)) * self.gamma
        return x + y.permute(0, 3, 1, 2)


class ConvNextStage(nn.Module):
    def __init__(self, cfg: dict, s: int):
        super().__init__()
        c, eps = cfg["cond_encoder"], cfg["norm_eps"]
        dims = c["dims"]
        if s > 0:
            # Transitions past the patch stride keep their norm but become a 1×1 stride-1 conv.
            k = 2 if cond_downsamples(cfg, s) else 1
            self.downsample = nn.Sequential(LayerNorm2d(dims[s - 1], eps=eps),
                                            nn.Conv2d(dims[s - 1], dims[s], k, stride=k))
        else:
            self.downsample = None
        self.blocks = nn.ModuleList(ConvNextBlock(dims[s], eps) for _ in range(c["depths"][s]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.downsample is not None:
            x = self.downsample(x)
        for block in self.blocks:
            x = block(x)
        return x


class ConvNextEncoder(nn.Module):
    """ConvNeXt over `C_T` at stride `patch`: `(B, 9, H, W)` → `(B, N, d)` (norm, then proj)."""

    def __init__(self, cfg: dict):
        super().__init__()
        dims, eps = cfg["cond_encoder"]["dims"], cfg["norm_eps"]
        self.stem = nn.Sequential(nn.Conv2d(9, dims[0], 4, stride=4), LayerNorm2d(dims[0], eps=eps))
        self.stages = nn.ModuleList(ConvNextStage(cfg, s) for s in range(4))
        self.norm = nn.LayerNorm(dims[3], eps=eps)
        self.proj = nn.Linear(dims[3], cfg["dim"])

    def forward(self, ct: torch.Tensor) -> torch.Tensor:
        x = self.stem(ct)
        for stage in self.stages:
            x = stage(x)
        return self.proj(self.norm(x.flatten(2).transpose(1, 2)))


# ---------------------------------------------------------------------------------------------
# Fusion (fusion.rs) and trunk (trunk.rs)
# ---------------------------------------------------------------------------------------------


class Fusion(Mlp):
    """Per-location `Linear(2d → d) – GELU – Linear(d → d)` on `[source token ; conditioning token]`."""

    def __init__(self, cfg: dict):
        d = cfg["dim"]
        super().__init__(2 * d, d, d)

    def forward(self, src_tokens: torch.Tensor, cond_tokens: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        return super().forward(torch.cat([src_tokens, cond_tokens], dim=-1))


class Trunk(nn.Module):
    """Registers prepended, pre-norm blocks with 2D RoPE on the patch tokens; the readout blocks'
    patch tokens go through the shared `norm` and become `(B, d, gh, gw)` maps."""

    def __init__(self, cfg: dict):
        super().__init__()
        t, d = cfg["trunk"], cfg["dim"]
        self.readouts = list(t["readouts"])
        self.head_dim = d // t["heads"]
        self.rope_base = t["rope_base"]
        self.registers = nn.Parameter(torch.zeros(1, t["registers"], d))
        self.blocks = nn.ModuleList(Block(d, t["heads"], t["mlp_ratio"], cfg["norm_eps"]) for _ in range(t["depth"]))
        self.norm = nn.LayerNorm(d, eps=cfg["norm_eps"])

    def forward(self, tokens: torch.Tensor, gh: int, gw: int) -> list[torch.Tensor]:
        b, n, d = tokens.shape
        r = self.registers.shape[1]
        rope = Rope2d(self.head_dim, gh, gw, self.rope_base, tokens.dtype)
        x = torch.cat([self.registers.expand(b, r, d), tokens], dim=1)
        outs = []
        for i, block in enumerate(self.blocks):
            x = block(x, rope, r)
            if i in self.readouts:
                patches = self.norm(x[:, r:])
                outs.append(patches.transpose(1, 2).reshape(b, d, gh, gw))
        return outs


# ---------------------------------------------------------------------------------------------
# DPT head (dpt.rs)
# ---------------------------------------------------------------------------------------------


def resize(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Bilinear, half-pixel centres (`align_corners=False`), no antialiasing."""
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return F.interpolate(x, size=size, mode="bilinear", align_corners=False)


class ResidualConvUnit(nn.Module):
    """`x + conv2(relu(conv1(relu(x))))`, 3×3 convs."""

    def __init__(self, f: int):
        super().__init__()
        self.conv1 = nn.Conv2d(f, f, 3, padding=1)
        self.conv2 = nn.Conv2d(f, f, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FeatureFusionBlock(nn.Module):
    """`path (+ resConfUnit1(skip))` → `resConfUnit2` → resize to `size` → `out_conv` (1×1)."""

    def __init__(self, f: int, with_skip: bool):
        super().__init__()
        if with_skip:
            self.resConfUnit1 = ResidualConvUnit(f)
        self.resConfUnit2 = ResidualConvUnit(f)
        self.out_conv = nn.Conv2d(f, f, 1)

    def forward(self, path: torch.Tensor, skip: torch.Tensor | None, size: tuple[int, int]) -> torch.Tensor:
        if skip is not None:
            path = path + self.resConfUnit1(skip)
        return self.out_conv(resize(self.resConfUnit2(path), size))


class Scratch(nn.Module):
    def __init__(self, cfg: dict):
        super().__init__()
        oc, f = cfg["head"]["out_channels"], cfg["head"]["features"]
        for k in range(1, 5):
            setattr(self, f"layer{k}_rn", nn.Conv2d(oc[k - 1], f, 3, padding=1, bias=False))
            # refinenet4 has no resConfUnit1 (DPT builds one and never uses it).
            setattr(self, f"refinenet{k}", FeatureFusionBlock(f, with_skip=k < 4))
        self.output_conv1 = nn.Conv2d(f, f // 2, 3, padding=1)
        self.output_conv2 = nn.Sequential(nn.Conv2d(f // 2, cfg["head"]["hidden"], 3, padding=1), nn.ReLU())


class DptHead(nn.Module):
    """Four readouts `(B, d, gh, gw)` → `F` `(B, C', H, W)` (Depth Anything v2 `DPTHead` layout)."""

    def __init__(self, cfg: dict):
        super().__init__()
        oc, d = cfg["head"]["out_channels"], cfg["dim"]
        self.projects = nn.ModuleList(nn.Conv2d(d, oc[i], 1) for i in range(4))
        self.resize_layers = nn.ModuleList([
            nn.ConvTranspose2d(oc[0], oc[0], 4, stride=4),
            nn.ConvTranspose2d(oc[1], oc[1], 2, stride=2),
            nn.Identity(),
            nn.Conv2d(oc[3], oc[3], 3, stride=2, padding=1),
        ])
        self.scratch = Scratch(cfg)

    def forward(self, readouts: list[torch.Tensor], h: int, w: int) -> torch.Tensor:
        s = self.scratch
        rn = [s.layer1_rn, s.layer2_rn, s.layer3_rn, s.layer4_rn]
        layers = [rn[i](self.resize_layers[i](self.projects[i](x))) for i, x in enumerate(readouts)]
        size = [tuple(t.shape[-2:]) for t in layers]
        path = s.refinenet4(layers[3], None, size[2])
        path = s.refinenet3(path, layers[2], size[1])
        path = s.refinenet2(path, layers[1], size[0])
        path = s.refinenet1(path, layers[0], (2 * size[0][0], 2 * size[0][1]))
        out = resize(s.output_conv1(path), (h, w))
        return s.output_conv2(out)


# ---------------------------------------------------------------------------------------------
# Modulation (modulation.rs) and the network (model.rs)
# ---------------------------------------------------------------------------------------------


class Modulation(nn.Module):
    """1×1 conv `C' → 6`: gain `g` (channels 0–2) and bias `b` (3–5)."""

    def __init__(self, hidden: int):
        super().__init__()
        self.conv = nn.Conv2d(hidden, 6, 1)

    def gain_bias(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        gb = self.conv(features)
        return gb[:, :3], gb[:, 3:]

    @staticmethod
    def apply(src: torch.Tensor, g: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return ((g + 1.0) * src + b).clamp(0.0, 1.0)


class PixlRelight(nn.Module):
    """`Î_T = clip((1 + g) ⊙ I_S + b, 0, 1)`; `src` `(B, 3, H, W)`, `ct` `(B, 9, H, W)`, any H, W."""

    def __init__(self, cfg: dict):
        super().__init__()
        self.cfg = validate(cfg)
        self.src_encoder = VitEncoder(self.cfg)
        self.cond_encoder = ConvNextEncoder(self.cfg)
        self.fuse = Fusion(self.cfg)
        self.trunk = Trunk(self.cfg)
        self.head = DptHead(self.cfg)
        self.modulation = Modulation(self.cfg["head"]["hidden"])

    def gain_bias(self, src: torch.Tensor, ct: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Unclipped gain and bias `(B, 3, H, W)` each."""
        h, w = src.shape[-2:]
        p = self.cfg["patch"]
        ph, pw = -(-h // p) * p, -(-w // p) * p
        # Bottom/right padding to a multiple of the patch size by edge replication.
        pad = (0, pw - w, 0, ph - h)
        src_p = F.pad(src, pad, mode="replicate") if pad != (0, 0, 0, 0) else src
        ct_p = F.pad(ct, pad, mode="replicate") if pad != (0, 0, 0, 0) else ct
        tokens = self.fuse(self.src_encoder(src_p), self.cond_encoder(ct_p))
        readouts = self.trunk(tokens, ph // p, pw // p)
        g, b = self.modulation.gain_bias(self.head(readouts, ph, pw))
        return g[:, :, :h, :w], b[:, :, :h, :w]

    def forward(self, src: torch.Tensor, ct: torch.Tensor) -> torch.Tensor:
        g, b = self.gain_bias(src, ct)
        return Modulation.apply(src, g, b)

    def forward_unclipped(self, src: torch.Tensor, ct: torch.Tensor) -> torch.Tensor:
        """`(1 + g) ⊙ I_S + b` before the clip (model.rs `forward_unclipped`), what training takes."""
        g, b = self.gain_bias(src, ct)
        return (g + 1.0) * src + b


# ---------------------------------------------------------------------------------------------
# Checkpoints
# ---------------------------------------------------------------------------------------------


def read_checkpoint(path: Path) -> tuple[dict, dict[str, torch.Tensor], dict]:
    """`(config, tensors, metadata)` of a `pixl` safetensors checkpoint."""
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata() or {}
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    if meta.get("format") != "pixlrelight" or "config" not in meta:
        raise SystemExit(f"{path}: not a pixlrelight checkpoint (metadata {sorted(meta)})")
    return json.loads(meta["config"]), tensors, meta


def load_model(path: Path) -> PixlRelight:
    cfg, tensors, _ = read_checkpoint(path)
    model = PixlRelight(cfg)
    model.load_state_dict({k: v.float() for k, v in tensors.items()}, strict=True)
    return model.eval()


def save_checkpoint(path: Path, tensors: dict[str, torch.Tensor], meta: dict) -> None:
    from safetensors.torch import save_file

    save_file({k: v.contiguous() for k, v in tensors.items()}, str(path), metadata=meta)


def perturb(tensors: dict[str, torch.Tensor], seed: int, scale: float) -> dict[str, torch.Tensor]:
    """Every tensor plus Gaussian noise, drawn from one generator in sorted-name order. The noise's
    std is `scale` times the tensor's own std, or for a constant tensor (zero-initialised
    biases and modulation conv, norms, `gamma`) `scale` times `1/√fan_in` (weights) or 0.1
    (vectors): every part of the network then affects the output while activations keep the
    scale of the initialisation (so the output is mostly unclipped)."""
    gen = torch.Generator().manual_seed(seed)
    out = {}
    for name in sorted(tensors):
        t = tensors[name].float()
        std = t.std().item() if t.numel() > 1 else 0.0
        if std > 0:
            ref = std
        elif t.dim() >= 2:
            ref = 1.0 / math.sqrt(t.numel() // t.shape[0])
        else:
            ref = 0.1
        noise = torch.randn(t.shape, generator=gen, dtype=torch.float32)
        out[name] = (t + scale * ref * noise).to(tensors[name].dtype)
    return out


# ---------------------------------------------------------------------------------------------
# Full-resolution path (fullres.rs): what `pixl relight --intrinsics` runs
# ---------------------------------------------------------------------------------------------


def working_size(width: int, height: int, max_side: int) -> tuple[int, int]:
    long, max_side = max(width, height), max(max_side, 1)
    if long <= max_side:
        return width, height
    scale = max_side / long

    def side(n: int) -> int:
        return max_side if n == long else min(max(int(math.floor(n * scale + 0.5)), 1), max_side)

    return side(width), side(height)


def area_matrix(n_in: int, n_out: int) -> torch.Tensor:
    """`(n_out, n_in)` box-filter weights: each output averages its footprint, weighted by overlap."""
    m = torch.zeros(n_out, n_in, dtype=torch.float64)
    scale = n_in / n_out
    for o in range(n_out):
        a, b = o * scale, (o + 1) * scale
        for i in range(min(int(math.floor(a)), n_in - 1), min(max(int(math.ceil(b)), int(math.floor(a)) + 1), n_in)):
            overlap = min(b, i + 1.0) - max(a, float(i))
            if overlap > 0:
                m[o, i] = overlap / (b - a)
    return m.float()


def area_resize(img: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """`(C, H, W)` → `(C, h, w)` area average (identity at the same size)."""
    if tuple(img.shape[-2:]) == (h, w):
        return img
    return area_matrix(img.shape[-2], h) @ img @ area_matrix(img.shape[-1], w).T


@torch.inference_mode()
def relight_full(model: PixlRelight, photo: torch.Tensor, ct: torch.Tensor, max_side: int) -> torch.Tensor:
    """`photo` `(3, H, W)` in [0, 1], `ct` `(9, H, W)` or at the working size → `(3, H, W)`: the
    network at the working size, its gain and bias resized bilinearly to the photo and applied there."""
    _, h, w = photo.shape
    ww, wh = working_size(w, h, max_side)
    if tuple(ct.shape[-2:]) not in ((h, w), (wh, ww)):
        raise SystemExit(f"C_T is {ct.shape[-1]}x{ct.shape[-2]}: give it at {w}x{h} or the working size {ww}x{wh}")
    src = area_resize(photo, wh, ww)[None]
    ct = area_resize(ct, wh, ww)[None]
    g, b = model.gain_bias(src, ct)
    g, b = resize(g, (h, w))[0], resize(b, (h, w))[0]
    return Modulation.apply(photo, g, b)


# ---------------------------------------------------------------------------------------------
# Image files
# ---------------------------------------------------------------------------------------------

CT_CHANNELS = [f"{g}.{c}" for g in ("albedo", "shading", "residual") for c in "RGB"]


def read_exr(path: Path) -> dict[str, np.ndarray]:
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        return {name: np.asarray(ch.pixels, dtype=np.float32) for name, ch in f.channels().items()}


def write_exr(path: Path, channels: dict[str, np.ndarray]) -> None:
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    chans = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}
    with OpenEXR.File(header, chans) as f:
        f.write(str(path))


def read_source(path: Path) -> torch.Tensor:
    """RGB `(3, H, W)` f32 clamped to [0, 1] (as `pixl relight` reads `--source`)."""
    ext = path.suffix.lower()
    if ext == ".npy":
        arr = np.load(path).astype(np.float32)
    elif ext == ".exr":
        ch = read_exr(path)
        if not all(c in ch for c in "RGB"):
            raise SystemExit(f"{path}: needs R, G, B channels, found {sorted(ch)}")
        arr = np.stack([ch["R"], ch["G"], ch["B"]])
    elif ext == ".png":
        from PIL import Image

        im = np.asarray(Image.open(path))
        scale = 65535.0 if im.dtype == np.uint16 else 255.0
        im = im.astype(np.float32) / scale
        im = np.repeat(im[..., None], 3, axis=-1) if im.ndim == 2 else im[..., :3]
        arr = im.transpose(2, 0, 1)
    else:
        raise SystemExit(f"{path}: source must be .exr, .png or .npy")
    return torch.from_numpy(np.ascontiguousarray(arr)).clamp(0.0, 1.0)


def read_ct(path: Path) -> torch.Tensor:
    """`C_T` `(9, H, W)`: an EXR with albedo.R … residual.B, or a `(9, H, W)` .npy."""
    if path.suffix.lower() == ".npy":
        return torch.from_numpy(np.load(path).astype(np.float32))
    ch = read_exr(path)
    missing = [c for c in CT_CHANNELS if c not in ch]
    if missing:
        raise SystemExit(f"{path}: missing C_T channels {missing}")
    return torch.from_numpy(np.stack([ch[c] for c in CT_CHANNELS]))


def write_rgb(path: Path, img: torch.Tensor) -> None:
    arr = img.detach().float().numpy()
    if path.suffix.lower() == ".npy":
        np.save(path, arr)
    else:
        write_exr(path, {"R": arr[0], "G": arr[1], "B": arr[2]})


# ---------------------------------------------------------------------------------------------
# Training step (pixl-train: loss.rs, optim.rs, recompute.rs; `pixl bench train-step`)
# ---------------------------------------------------------------------------------------------

ADAMW_BETAS = (0.9, 0.95)  # AdamWConfig::default()
ADAMW_EPS = 1e-8
ADAMW_WEIGHT_DECAY = 0.05
CLIP_NORM = 1.0
BENCH_LR = 1e-4  # the fixed rate of `pixl bench train-step`


def decays(name: str, shape) -> bool:
    """optim.rs `decays`: weight decay for tensors of rank ≥ 2 except the register tokens, the
    position embeddings, layer scales (`gamma`) and biases."""
    exempt = "registers" in name or "pos_embed" in name or name.endswith("gamma")
    return len(shape) >= 2 and not exempt and not name.endswith(".bias")


def train_loss(pred: torch.Tensor, tgt: torch.Tensor) -> torch.Tensor:
    """loss.rs `loss` with `Objective::l1_only()`: `pred` is the unclipped output; the L1 (mean
    absolute error over all `B·3·H·W` values) is taken on its clip to [0, 1], so saturated pixels
    pass no gradient."""
    return (pred.clamp(0.0, 1.0) - tgt).abs().mean()


def make_adamw(model: nn.Module, lr: float, impl: str = "default") -> torch.optim.AdamW:
    """`torch.optim.AdamW` with our configuration: two groups, decayed (per `decays`) and not."""
    groups: dict[bool, list[nn.Parameter]] = {True: [], False: []}
    for name, p in model.named_parameters():
        groups[decays(name, p.shape)].append(p)
    kw = {} if impl == "default" else {impl: True}  # "foreach" or "fused"
    return torch.optim.AdamW(
        [{"params": groups[True], "weight_decay": ADAMW_WEIGHT_DECAY},
         {"params": groups[False], "weight_decay": 0.0}],
        lr=lr, betas=ADAMW_BETAS, eps=ADAMW_EPS, **kw)


def check_twin(model: nn.Module, tensors: dict[str, torch.Tensor], cfg: dict) -> tuple[int, int]:
    """The twin's parameters are exactly the checkpoint's tensors (names, shapes); returns
    `(tensor count, parameter count)`."""
    named = dict(model.named_parameters())
    missing, extra = sorted(set(tensors) - set(named)), sorted(set(named) - set(tensors))
    if missing or extra:
        raise SystemExit(f"the PyTorch twin differs from the checkpoint: missing {missing[:5]}, extra {extra[:5]}")
    for k, t in tensors.items():
        if tuple(named[k].shape) != tuple(t.shape):
            raise SystemExit(f"{k}: twin shape {tuple(named[k].shape)}, checkpoint {tuple(t.shape)}")
    if list(model.buffers()):
        raise SystemExit("the PyTorch twin has buffers the checkpoint does not store")
    return len(named), sum(p.numel() for p in named.values())


def read_tensors(path: Path) -> tuple[dict[str, torch.Tensor], dict]:
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        return {k: f.get_tensor(k) for k in f.keys()}, (f.metadata() or {})


# ---------------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------------


def parse_size(s: str) -> tuple[int, int]:
    w, h = s.lower().split("x")
    return int(w), int(h)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux


def cmd_run(args) -> None:
    model = load_model(args.weights)
    out = relight_full(model, read_source(args.source), read_ct(args.intrinsics), args.max_side)
    write_rgb(args.out, out)
    print(f"wrote {args.out} ({out.shape[2]}x{out.shape[1]})")


def cmd_parity(args) -> None:
    model = load_model(args.weights)
    photo, ct = read_source(args.source), read_ct(args.intrinsics)
    ours = relight_full(model, photo, ct, args.max_side)
    ref = read_source(args.reference) if args.reference.suffix.lower() != ".npy" else \
        torch.from_numpy(np.load(args.reference).astype(np.float32))
    if ref.shape != ours.shape:
        raise SystemExit(f"shape mismatch: torch {tuple(ours.shape)}, reference {tuple(ref.shape)}")
    diff = (ours - ref).abs()
    # Pixels strictly inside (0, 1) in both carry the network's gain and bias unclipped.
    inside = ((ours > 0) & (ours < 1) & (ref > 0) & (ref < 1)).float().mean().item()
    changed = (ours - photo).abs().max().item()
    cfg = model.cfg
    print(f"parity {args.weights.name}: {photo.shape[2]}x{photo.shape[1]}, dim {cfg['dim']}: "
          f"max |torch - pixl| = {diff.max().item():.3e}, mean {diff.mean().item():.3e}; "
          f"{100 * inside:.1f}% of samples unclipped; max |output - source| = {changed:.3f}")
    if args.out is not None:
        write_rgb(args.out, ours)
    if not diff.max().item() <= args.tol:
        print(f"FAIL: max abs difference above tolerance {args.tol:g}", file=sys.stderr)
        sys.exit(1)
    if changed == 0.0:
        print("FAIL: the output equals the source (unperturbed weights?); parity proves nothing", file=sys.stderr)
        sys.exit(1)


def cmd_time(args) -> None:
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    if args.weights is not None:
        model = load_model(args.weights)
    else:
        model = PixlRelight(preset(args.config)).eval()  # PyTorch's default init; values do not matter for timing
    if args.int8:
        # PyTorch's dynamic 8-bit quantization (fbgemm/x86): every nn.Linear, weights per tensor,
        # activations per call; the counterpart of `pixl bench model --int8`.
        model = torch.ao.quantization.quantize_dynamic(model, {nn.Linear}, dtype=torch.qint8)
    w, h = parse_size(args.size)
    gen = torch.Generator().manual_seed(1)
    src = torch.rand(1, 3, h, w, generator=gen)
    ct = torch.rand(1, 9, h, w, generator=gen)
    runs = []
    with torch.inference_mode():
        for _ in range(args.warmups):
            model(src, ct)
        for _ in range(args.runs):
            t = time.perf_counter()
            out = model(src, ct)
            runs.append((time.perf_counter() - t) * 1e3)
            del out
    result = {
        "impl": "torch", "torch": torch.__version__, "int8": args.int8, "config": args.config if args.weights is None else str(args.weights),
        "width": w, "height": h, "threads": torch.get_num_threads(), "warmups": args.warmups, "runs_ms": runs,
        "median_ms": statistics.median(runs), "min_ms": min(runs), "mean_ms": statistics.fmean(runs),
        "peak_rss_mb": peak_rss_mb(),
    }
    if args.json:
        print(json.dumps(result))
    else:
        print(f"torch {result['config']}, {w}x{h}, f32, {result['threads']} threads: median {result['median_ms']:.1f} ms, "
              f"min {result['min_ms']:.1f} ms ({args.runs} runs after {args.warmups} warm-ups); "
              f"peak RSS {result['peak_rss_mb']:.0f} MB")


def cmd_perturb(args) -> None:
    _, tensors, meta = read_checkpoint(args.weights)
    save_checkpoint(args.out, perturb(tensors, args.seed, args.scale), meta)
    print(f"wrote {args.out} ({len(tensors)} tensors perturbed, seed {args.seed}, scale {args.scale:g})")


def cmd_inputs(args) -> None:
    w, h = parse_size(args.size)
    gen = torch.Generator().manual_seed(args.seed)
    src = torch.rand(3, h, w, generator=gen).numpy()
    ct = torch.rand(9, h, w, generator=gen).numpy()
    write_exr(args.source, {"R": src[0], "G": src[1], "B": src[2]})
    write_exr(args.intrinsics, {name: ct[i] for i, name in enumerate(CT_CHANNELS)})
    print(f"wrote {args.source} and {args.intrinsics} ({w}x{h}, seed {args.seed})")


def cmd_train_step(args) -> None:
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    if args.weights is not None:
        cfg, tensors, _ = read_checkpoint(args.weights)
        model = PixlRelight(cfg)
        model.load_state_dict({k: v.float() for k, v in tensors.items()}, strict=True)
        n_tensors, n_params = check_twin(model, tensors, cfg)
        del tensors
        name = str(args.weights)
    else:
        model = PixlRelight(preset(args.config))  # PyTorch's default init; values do not matter for timing
        n_tensors, n_params = len(list(model.parameters())), sum(p.numel() for p in model.parameters())
        name = args.config
    model.train()
    opt = make_adamw(model, BENCH_LR, args.adamw)
    params = list(model.parameters())
    w, h = parse_size(args.size)
    b = args.batch
    gen = torch.Generator().manual_seed(1)
    src = torch.rand(b, 3, h, w, generator=gen)
    ct = torch.rand(b, 9, h, w, generator=gen)
    tgt = torch.rand(b, 3, h, w, generator=gen)

    def step() -> tuple[float, float, float, float]:
        t0 = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        loss = train_loss(model.forward_unclipped(src, ct), tgt)
        t1 = time.perf_counter()
        loss.backward()
        t2 = time.perf_counter()
        torch.nn.utils.clip_grad_norm_(params, CLIP_NORM)
        opt.step()
        t3 = time.perf_counter()
        return (t3 - t0) * 1e3, (t1 - t0) * 1e3, (t2 - t1) * 1e3, loss.item()

    for _ in range(args.warmups):
        step()
    runs, fwd, bwd, upd = [], [], [], []
    last_loss = float("nan")
    for _ in range(args.runs):
        total, f, bw, last_loss = step()
        runs.append(total)
        fwd.append(f)
        bwd.append(bw)
        upd.append(total - f - bw)
    med = statistics.median
    result = {
        "impl": "torch", "torch": torch.__version__, "config": name, "tensors": n_tensors, "params": n_params,
        "width": w, "height": h, "batch": b, "threads": torch.get_num_threads(), "adamw": args.adamw,
        "warmups": args.warmups, "runs_ms": runs, "median_ms": med(runs), "min_ms": min(runs),
        "mean_ms": statistics.fmean(runs),
        "split_median_ms": {"forward": med(fwd), "backward": med(bwd), "clip_optim": med(upd)},
        "last_loss": last_loss, "peak_rss_mb": peak_rss_mb(),
    }
    if args.json:
        print(json.dumps(result))
    else:
        s = result["split_median_ms"]
        print(f"torch {name} ({n_params / 1e6:.2f} M params in {n_tensors} tensors), batch {b} at {w}x{h}, f32, "
              f"{result['threads']} threads: per step " + " ".join(f"{r:.1f}" for r in runs) + " ms")
        print(f"  median {result['median_ms']:.1f} ms (min {result['min_ms']:.1f}; {args.runs} runs after "
              f"{args.warmups} warm-ups): forward + loss {s['forward']:.1f}, backward {s['backward']:.1f}, "
              f"clip + AdamW {s['clip_optim']:.1f} ms (medians); last loss {last_loss:.4f}; "
              f"peak RSS {result['peak_rss_mb']:.0f} MB")


def cmd_grads(args) -> None:
    dtype = {"f64": torch.float64, "f32": torch.float32}[args.dtype]
    cfg, tensors, _ = read_checkpoint(args.weights)
    model = PixlRelight(cfg)
    model.load_state_dict({k: v.float() for k, v in tensors.items()}, strict=True)
    n_tensors, n_params = check_twin(model, tensors, cfg)
    model = model.to(dtype).train()
    inputs, _ = read_tensors(args.inputs)
    try:
        src, ct, tgt = (inputs[k].to(dtype) for k in ("src", "ct", "tgt"))
    except KeyError as e:
        raise SystemExit(f"{args.inputs}: no tensor {e} (needs src, ct, tgt)")
    if src.shape[1] != 3 or ct.shape[1] != 9 or tgt.shape != src.shape or ct.shape[2:] != src.shape[2:]:
        raise SystemExit(f"inputs of shapes src {tuple(src.shape)}, ct {tuple(ct.shape)}, tgt {tuple(tgt.shape)}")
    t = time.perf_counter()
    pred = model.forward_unclipped(src, ct)
    loss = train_loss(pred, tgt)
    loss.backward()
    secs = time.perf_counter() - t
    inside = ((pred > 0) & (pred < 1)).to(dtype).mean().item()
    grads = {}
    for name, p in model.named_parameters():
        if p.grad is None:
            print(f"torch: {name} got no gradient", file=sys.stderr)
            continue
        grads[name] = p.grad.detach().contiguous()
    meta = {"loss": repr(loss.item()), "impl": "torch", "dtype": args.dtype}
    from safetensors.torch import save_file

    save_file(grads, str(args.out), metadata=meta)
    b, _, h, w = src.shape
    print(f"torch {args.dtype}: loss {loss.item():.6e}, {len(grads)} of {n_tensors} gradients ({n_params / 1e6:.2f} M "
          f"values) written to {args.out} (batch {b}, {w}x{h}; {100 * inside:.1f}% of outputs inside (0, 1); "
          f"forward + backward {secs:.1f} s)")


def cmd_compare_grads(args) -> None:
    a, meta_a = read_tensors(args.a)
    b, meta_b = read_tensors(args.b)
    rows = []  # (rel, name, max_abs, |b|, numel)
    bad = []
    num_all = den_all = 0.0
    for name in sorted(set(a) | set(b)):
        if name not in a or name not in b:
            bad.append(f"{name}: only in {args.a if name in a else args.b}")
            continue
        x, y = a[name].double(), b[name].double()
        if x.shape != y.shape:
            bad.append(f"{name}: shapes {tuple(x.shape)} vs {tuple(y.shape)}")
            continue
        d = x - y
        num, den = d.square().sum().item(), y.square().sum().item()
        num_all += num
        den_all += den
        rel = math.sqrt(num / den) if den > 0 else math.sqrt(num)  # absolute where the reference is 0
        if not torch.isfinite(x).all():
            rel = math.inf
        rows.append((rel, name, d.abs().max().item(), math.sqrt(den), y.numel()))
    rows.sort(key=lambda r: (-r[0] if not math.isnan(r[0]) else -math.inf, r[1]))
    over = [r for r in rows if not r[0] <= args.tol]
    print(f"gradients: {args.a} against {args.b}, relative L2 error ‖a − b‖₂ / ‖b‖₂ per tensor")
    print(f"| tensor | numel | ‖b‖₂ | max abs diff | rel L2 |")
    print(f"|---|---|---|---|---|")
    for rel, name, mx, nb, n in rows[:args.top]:
        print(f"| {name} | {n} | {nb:.3e} | {mx:.3e} | {rel:.3e}{' FAIL' if not rel <= args.tol else ''} |")
    rels = [r[0] for r in rows]
    if rows:
        glob = math.sqrt(num_all / den_all) if den_all > 0 else math.sqrt(num_all)
        print(f"{len(rows)} tensors compared: max rel {max(rels):.3e}, median {statistics.median(rels):.3e}, "
              f"all gradients together {glob:.3e}; {len(over)} above tol {args.tol:g}")
    if "loss" in meta_a and "loss" in meta_b:
        la, lb = float(meta_a["loss"]), float(meta_b["loss"])
        print(f"loss: {la:.9e} vs {lb:.9e} (relative difference {abs(la - lb) / max(abs(lb), 1e-300):.3e})")
    for line in bad:
        print(f"MISMATCH {line}")
    if over or bad or not rows:
        print(f"FAIL: {len(over)} tensors above tol {args.tol:g}, {len(bad)} missing or misshapen", file=sys.stderr)
        sys.exit(1)
    print(f"PASS: every gradient within relative L2 error {args.tol:g}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)

    def io_args(p):
        p.add_argument("--weights", type=Path, required=True)
        p.add_argument("--source", type=Path, required=True)
        p.add_argument("--intrinsics", type=Path, required=True)
        p.add_argument("--max-side", type=int, default=1024, help="working size's long side (as pixl relight)")
        p.add_argument("--threads", type=int, default=None)

    p = sub.add_parser("run", help="relight a source under a C_T")
    io_args(p)
    p.add_argument("--out", type=Path, required=True, help=".exr (R, G, B f32) or .npy (3, H, W)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("parity", help="compare with a pixl relight output")
    io_args(p)
    p.add_argument("--reference", type=Path, required=True, help="pixl's output (.exr or .npy)")
    p.add_argument("--tol", type=float, default=1e-4)
    p.add_argument("--out", type=Path, default=None, help="also write the torch output here")
    p.set_defaults(func=cmd_parity)

    p = sub.add_parser("time", help="time forward passes (pixl bench model protocol)")
    p.add_argument("--weights", type=Path, default=None, help="a checkpoint; else --config with default init")
    p.add_argument("--config", default="tiny", help="preset (tiny, small, paper) when no --weights")
    p.add_argument("--size", default="512x512", help="WIDTHxHEIGHT")
    p.add_argument("--warmups", type=int, default=2)
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--threads", type=int, default=torch.get_num_threads())
    p.add_argument("--int8", action="store_true", help="dynamic 8-bit quantization of every nn.Linear")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_time)

    p = sub.add_parser("perturb", help="add seeded noise to every tensor of a checkpoint")
    p.add_argument("--weights", type=Path, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scale", type=float, default=0.5, help="noise std relative to the tensor's std (see perturb())")
    p.set_defaults(func=cmd_perturb)

    p = sub.add_parser("inputs", help="write a random source and C_T as EXR")
    p.add_argument("--size", default="256x256")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--source", type=Path, required=True)
    p.add_argument("--intrinsics", type=Path, required=True)
    p.set_defaults(func=cmd_inputs)

    p = sub.add_parser("train-step", help="time training steps (pixl bench train-step protocol)")
    p.add_argument("--weights", type=Path, default=None, help="a checkpoint; else --config with default init")
    p.add_argument("--config", default="tiny", help="preset (tiny, small, paper) when no --weights")
    p.add_argument("--size", default="256x256", help="crop WIDTHxHEIGHT")
    p.add_argument("--batch", type=int, default=2)
    p.add_argument("--warmups", type=int, default=2)
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--threads", type=int, default=torch.get_num_threads())
    p.add_argument("--adamw", choices=["default", "foreach", "fused"], default="default",
                   help="torch.optim.AdamW implementation (default: PyTorch's choice, per-tensor loop on CPU)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_train_step)

    p = sub.add_parser("grads", help="loss gradients of every parameter (float64 reference)")
    p.add_argument("--weights", type=Path, required=True)
    p.add_argument("--inputs", type=Path, required=True, help="safetensors with src, ct, tgt")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--dtype", choices=["f64", "f32"], default="f64")
    p.add_argument("--threads", type=int, default=None)
    p.set_defaults(func=cmd_grads)

    p = sub.add_parser("compare-grads", help="per-tensor relative error of two gradient files")
    p.add_argument("a", type=Path, help="the gradients checked (e.g. pixl's)")
    p.add_argument("b", type=Path, help="the reference (e.g. torch f64)")
    p.add_argument("--tol", type=float, default=1e-4)
    p.add_argument("--top", type=int, default=10, help="rows printed, worst first")
    p.set_defaults(func=cmd_compare_grads)

    args = ap.parse_args(argv)
    if getattr(args, "threads", None) and args.cmd not in ("time", "train-step"):
        torch.set_num_threads(args.threads)
    args.func(args)


if __name__ == "__main__":
    main()
