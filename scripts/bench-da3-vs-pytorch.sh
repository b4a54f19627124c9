#!/usr/bin/env bash
# DA3 network forward, candle port vs the official PyTorch model, same input sizes, same threads,
# random weights of the released da3metric-large architecture (ViT-L/14 + DPT), f32, CPU.
#
# usage: scripts/bench-da3-vs-pytorch.sh [--threads T] [--iters N] [--rounds R] [--size WxH ...] [--tiny]
#   --threads  threads for both (RAYON_NUM_THREADS / torch.set_num_threads); default: nproc
#   --iters    timed forwards per size and process (default 5; one untimed warm-up before)
#   --rounds   processes per side, run alternately candle, torch, candle, ... (default 3)
#   --size     network input WxH, multiples of 14 (default 504x378 and 504x504)
#   --tiny     the test fixtures' tiny architecture (a smoke test of this script)
# env: PYTHON  a Python with torch and depth-anything-3==0.1.1 (see scripts/fixtures/da3.py)
#
# Each process prints its own median per size (model construction excluded) and its peak RSS.
# PyTorch runs the network in f32 without the official API's autocast, as the port does.
set -euo pipefail
cd "$(dirname "$0")/.."

THREADS=$(nproc)
ITERS=5
ROUNDS=3
SIZES=()
TINY=""
while [ $# -gt 0 ]; do
  case "$1" in
    --threads) THREADS=$2; shift 2 ;;
    --iters) ITERS=$2; shift 2 ;;
    --rounds) ROUNDS=$2; shift 2 ;;
    --size) SIZES+=("$2"); shift 2 ;;
    --tiny) TINY=1; shift ;;
    *) echo "unknown argument $1" >&2; exit 2 ;;
  esac
done
[ ${#SIZES[@]} -eq 0 ] && SIZES=(504x378 504x504)
PYTHON=${PYTHON:-python3}

cargo build --release -q -p pixl-estimate --example bench_da3
BIN=${CARGO_TARGET_DIR:-target}/release/examples/bench_da3

size_args=()
for s in "${SIZES[@]}"; do size_args+=(--size "$s"); done

run_candle() {
  RAYON_NUM_THREADS=$THREADS "$BIN" "${size_args[@]}" --iters "$ITERS" ${TINY:+--tiny}
}

run_torch() {
  OMP_NUM_THREADS=$THREADS "$PYTHON" - "$THREADS" "$ITERS" "${TINY:-0}" "${SIZES[@]}" <<'PY'
import resource, sys, time
import torch
from depth_anything_3.cfg import create_object, load_config
from depth_anything_3.registry import MODEL_REGISTRY

threads, iters, tiny, sizes = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3] == "1", sys.argv[4:]
torch.set_num_threads(threads)
torch.manual_seed(0)
if tiny:
    from depth_anything_3.model.da3 import DepthAnything3Net
    from depth_anything_3.model.dinov2.dinov2 import DinoV2
    from depth_anything_3.model.dinov2.vision_transformer import DinoVisionTransformer
    from depth_anything_3.model.dpt import DPT
    net = DinoV2(name="vits", out_layers=[1, 2, 3, 4], alt_start=-1, qknorm_start=-1, rope_start=-1, cat_token=False)
    net.pretrained = DinoVisionTransformer(img_size=70, patch_size=14, embed_dim=32, depth=6, num_heads=4,
                                           mlp_ratio=4, ffn_layer="mlp", cat_token=False)
    model = DepthAnything3Net(net=net, head=DPT(dim_in=32, output_dim=1, features=16, out_channels=[8, 16, 24, 32]))
else:
    model = create_object(load_config(MODEL_REGISTRY["da3metric-large"]))
model = model.eval().float()
with torch.inference_mode():
    for s in sizes:
        w, h = map(int, s.split("x"))
        x = torch.randn(1, 1, 3, h, w)
        model(x)
        times = []
        for _ in range(iters):
            t = time.perf_counter()
            model(x)
            times.append((time.perf_counter() - t) * 1e3)
        times.sort()
        print(f"torch  da3 forward {w}x{h}: median {times[len(times) // 2]:.0f} ms "
              f"(min {times[0]:.0f}, max {times[-1]:.0f}, {len(times)} runs, {threads} threads)")
print(f"torch  peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
PY
}

echo "# $(date -u +%Y-%m-%dT%H:%MZ), $(lscpu | sed -n 's/^Model name: *//p'), threads $THREADS"
for r in $(seq "$ROUNDS"); do
  echo "## round $r"
  run_candle
  run_torch 2>&1 | grep -E '^torch'
done
