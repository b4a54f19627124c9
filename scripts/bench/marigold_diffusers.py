#!/usr/bin/env python3
"""One photo through diffusers' MarigoldIntrinsicsPipeline or MarigoldNormalsPipeline (the class named by
the checkpoint's model_index.json), on the CPU in f32: the yardstick for
`pixl estimate materials|lighting|normals` in scripts/bench-marigold.sh.

    usage: marigold_diffusers.py CHECKPOINT_DIR PHOTO [--res 512] [--steps 1] [--ensemble 1] [--threads 2]

CHECKPOINT_DIR is a diffusers pipeline folder with `*.fp16.safetensors` weights (as written by
marigold_random_checkpoint.py, or a downloaded prs-eth/marigold-iid-*-v1-1 or prs-eth/marigold-normals-v1-1); they
are loaded with
variant="fp16" and torch_dtype=float32, i.e. upcast to f32 as pixl does. Prints the load time, the
time of the pipeline call alone (preprocessing, VAE encode, denoising, VAE decode, resize back to the
photo's size) and the process's peak RSS. Not run by CI; nothing is downloaded.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time

os.environ.setdefault("HF_HUB_OFFLINE", "1")
T_START = time.perf_counter()

import torch  # noqa: E402
from PIL import Image  # noqa: E402

from diffusers import MarigoldIntrinsicsPipeline, MarigoldNormalsPipeline  # noqa: E402

PIPELINES = {c.__name__: c for c in (MarigoldIntrinsicsPipeline, MarigoldNormalsPipeline)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("checkpoint")
    ap.add_argument("photo")
    ap.add_argument("--res", type=int, default=512)
    ap.add_argument("--steps", type=int, default=1)
    ap.add_argument("--ensemble", type=int, default=1)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t_import = time.perf_counter() - T_START

    with open(os.path.join(args.checkpoint, "model_index.json")) as f:
        class_name = json.load(f)["_class_name"]
    if class_name not in PIPELINES:
        raise SystemExit(f"{args.checkpoint}: {class_name} is not one of {sorted(PIPELINES)}")
    t0 = time.perf_counter()
    pipe = PIPELINES[class_name].from_pretrained(args.checkpoint, variant="fp16", torch_dtype=torch.float32)
    pipe.set_progress_bar_config(disable=True)
    dtypes = {p.dtype for m in (pipe.unet, pipe.vae, pipe.text_encoder) for p in m.parameters()}
    assert dtypes == {torch.float32}, dtypes
    t_load = time.perf_counter() - t0

    image = Image.open(args.photo).convert("RGB")
    gen = torch.Generator().manual_seed(args.seed)
    t0 = time.perf_counter()
    with torch.inference_mode():
        out = pipe(image, num_inference_steps=args.steps, ensemble_size=args.ensemble,
                   processing_resolution=args.res, match_input_resolution=True, batch_size=1,
                   generator=gen, output_type="np")
    t_call = time.perf_counter() - t0
    pred = out.prediction
    finite = bool(torch.isfinite(torch.as_tensor(pred)).all())
    rss_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    what = f"{pipe.n_targets} targets" if hasattr(pipe, "n_targets") else "normals"
    print(f"diffusers marigold {what}, {image.size[0]}x{image.size[1]} at res {args.res}, "
          f"{args.steps} steps x {args.ensemble}, {args.threads} threads: import {t_import:.1f} s, "
          f"load {t_load:.1f} s, call {t_call:.2f} s, peak RSS {rss_gb:.2f} GB, "
          f"prediction {tuple(pred.shape)} finite {finite}", flush=True)


if __name__ == "__main__":
    main()
