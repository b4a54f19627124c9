#!/usr/bin/env bash
# Marigold-IID on the CPU at the REAL model sizes (random weights): wall time and peak memory per
# photo of `pixl estimate materials` (Appearance) and `pixl estimate lighting` (Lighting), and one
# side by side against diffusers' MarigoldIntrinsicsPipeline on the same photo and threads.
#
# Not run by CI. Run by hand from anywhere; it needs ~5.5 GB of disk for the two random checkpoints,
# ~6-8 GB of RAM, and minutes per run on a small CPU:
#
#   scripts/bench-marigold.sh [--threads T] [--photo PNG] [--weights DIR] [--bin PIXL] [--quick]
#     --threads  RAYON_NUM_THREADS for pixl, torch.set_num_threads for diffusers (default: nproc)
#     --photo    input photo (default: a 640x480 crop of crates/pixl-studio/studio.png, written to /tmp)
#     --weights  folder of the checkpoints: DIR/marigold-appearance, DIR/marigold-lighting
#                (default /work/bench-weights; built once with scripts/bench/marigold_random_checkpoint.py
#                when missing)
#     --bin      the pixl binary (default target/release/pixl, else target/debug/pixl; the dev profile
#                builds the dependencies - candle, gemm - at opt-level 3, where the time goes)
#     --quick    only Appearance and Lighting at 512 px, 1 step, and the diffusers comparison
# env: PYTHON  a Python with torch 2.15, diffusers 0.42.1, transformers 5.24 (default /work/venv-ref/bin/python;
#              see scripts/fixtures/marigold.py for the versions)
#
# The weights are random (the libraries' default initialisation, stored as *.fp16.safetensors and
# upcast to f32 by both loaders), so the maps are meaningless; the time and memory are the real
# model's: UNet 0.87 B, VAE 84 M, CLIP text encoder 0.34 B parameters. Each command runs under
# /usr/bin/time -v (wall time and "Maximum resident set size"); pixl's first load of a checkpoint
# writes the empty-prompt embedding cache beside the weights, so one untimed warm-up per model runs
# first. The diffusers script prints its pipeline call time separately (load excluded); pixl's
# figure is the whole command (load included), as is the diffusers process's wall time.
set -euo pipefail
cd "$(dirname "$0")/.."

THREADS=$(nproc)
PHOTO=""
WEIGHTS=/work/bench-weights
BIN=""
QUICK=""
while [ $# -gt 0 ]; do
  case "$1" in
    --threads) THREADS=$2; shift 2 ;;
    --photo) PHOTO=$2; shift 2 ;;
    --weights) WEIGHTS=$2; shift 2 ;;
    --bin) BIN=$2; shift 2 ;;
    --quick) QUICK=1; shift ;;
    *) echo "unknown argument $1" >&2; exit 2 ;;
  esac
done
PYTHON=${PYTHON:-/work/venv-ref/bin/python}
if [ -z "$BIN" ]; then
  BIN=target/release/pixl
  [ -x "$BIN" ] || BIN=target/debug/pixl
fi
[ -x "$BIN" ] || { echo "no pixl binary at $BIN (cargo build -p pixl-cli first)" >&2; exit 1; }

if [ -z "$PHOTO" ]; then
  PHOTO=/tmp/bench-marigold-photo.png
  "$PYTHON" - "$PHOTO" <<'PY'
import sys
from PIL import Image
im = Image.open("crates/pixl-studio/studio.png").convert("RGB")
w, h = im.size
cw = h * 4 // 3
x0 = (w - cw) // 2
im.crop((x0, 0, x0 + cw, h)).resize((640, 480), Image.LANCZOS).save(sys.argv[1])
PY
fi

for kind in appearance lighting; do
  if [ ! -f "$WEIGHTS/marigold-$kind/unet/diffusion_pytorch_model.fp16.safetensors" ]; then
    echo "== building random checkpoint $WEIGHTS/marigold-$kind"
    "$PYTHON" scripts/bench/marigold_random_checkpoint.py "$kind" "$WEIGHTS/marigold-$kind"
  fi
done

OUT=$(mktemp -d)
trap 'rm -rf "$OUT"' EXIT

# run LABEL CMD...: one timed run; prints wall s and peak RSS GB.
run() {
  local label=$1; shift
  /usr/bin/time -v "$@" >"$OUT/log" 2>&1 || { cat "$OUT/log" >&2; echo "$label: FAILED" >&2; return 1; }
  local wall rss
  wall=$(awk -F': ' '/Elapsed \(wall clock\)/ {n = split($2, a, ":"); s = 0; for (i = 1; i <= n; i++) s = s * 60 + a[i]; print s}' "$OUT/log")
  rss=$(awk -F': ' '/Maximum resident set size/ {printf "%.2f", $2 / 1024 / 1024}' "$OUT/log")
  grep -E '^diffusers marigold' "$OUT/log" || true
  printf '| %s | %s | %s |\n' "$label" "$wall" "$rss"
}

pixl() {  # pixl SUBCOMMAND RES STEPS
  # materials writes a folder of maps (--force: replace them); lighting writes one .exr file.
  local out=("$OUT/materials" --force)
  [ "$1" = lighting ] && out=("$OUT/lighting.exr")
  rm -f "$OUT/lighting.exr"
  RAYON_NUM_THREADS=$THREADS "$BIN" estimate "$1" "$PHOTO" -o "${out[@]}" --quiet \
    --models "$WEIGHTS" --offline --res "$2" --steps "$3"
}

echo "machine: $(lscpu | sed -n 's/^Model name: *//p'), $(nproc) cores; threads $THREADS; $(date -u +%F); $BIN"
echo "== warm-up (writes the empty-prompt embedding caches)"
pixl materials 64 1 >/dev/null
pixl lighting 64 1 >/dev/null

echo "| command | wall s | peak RSS GB |"
echo "|---|---|---|"
run "pixl estimate materials --res 512 --steps 1" pixl materials 512 1
if [ -z "$QUICK" ]; then
  run "pixl estimate materials --res 512 --steps 4" pixl materials 512 4
  run "pixl estimate materials --res 768 --steps 1" pixl materials 768 1
fi
run "pixl estimate lighting --res 512 --steps 1" pixl lighting 512 1
if [ -z "$QUICK" ]; then
  run "pixl estimate materials --res 768 --steps 4" pixl materials 768 4
fi

echo "== side by side, Appearance 512 px, 1 step, ensemble 1 (A B A B)"
for _ in 1 2; do
  run "pixl estimate materials --res 512 --steps 1" pixl materials 512 1
  run "diffusers MarigoldIntrinsicsPipeline (whole process)" \
    env OMP_NUM_THREADS="$THREADS" "$PYTHON" scripts/bench/marigold_diffusers.py \
    "$WEIGHTS/marigold-appearance" "$PHOTO" --res 512 --steps 1 --ensemble 1 --threads "$THREADS"
done
