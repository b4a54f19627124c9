#!/usr/bin/env bash
# Marigold on the CPU at the REAL model sizes (random weights): wall time and peak memory per photo
# of `pixl estimate materials` (IID Appearance), `pixl estimate lighting` (IID Lighting) and
# `pixl estimate normals` (Normals), and side by side against diffusers' MarigoldIntrinsicsPipeline
# and MarigoldNormalsPipeline on the same photo and threads, with each side's load time.
#
# Not run by CI. Run by hand from anywhere; it needs ~8 GB of disk for the three random checkpoints,
# ~6-8 GB of RAM, and minutes per run on a small CPU:
#
#   scripts/bench-marigold.sh [--threads T] [--photo PNG] [--weights DIR] [--bin PIXL] [--quick]
#                             [--only KINDS] [--res PX]
#     --threads  RAYON_NUM_THREADS for pixl, torch.set_num_threads for diffusers (default: nproc)
#     --photo    input photo (default: a 640x480 crop of crates/pixl-studio/studio.png, written to /tmp)
#     --weights  folder of the checkpoints: DIR/marigold-appearance, DIR/marigold-lighting,
#                DIR/marigold-normals (default /work/bench-weights; built once with
#                scripts/bench/marigold_random_checkpoint.py when missing)
#     --bin      the pixl binary (default target/release/pixl, else target/debug/pixl; the dev profile
#                builds the dependencies - candle, gemm - at opt-level 3, where the time goes)
#     --quick    only the --res px, --steps rows per model, and the diffusers comparisons
#     --only     comma-separated subset of appearance,lighting,normals (default: all three); the
#                side by side runs for appearance and normals when they are in it
#     --res      the processing resolution of the --quick rows and the side by side (default 512;
#                a multiple of 8 - a small one, e.g. 64, is a quick check that the script works)
#     --steps    denoising steps of the --quick rows and the side by side (default 1)
# env: PYTHON  a Python with torch 2.15, diffusers 0.42.1, transformers 5.24 (default /work/venv-ref/bin/python;
#              see scripts/fixtures/marigold.py for the versions)
#
# The weights are random (the libraries' default initialisation, stored as *.fp16.safetensors and
# upcast to f32 by both loaders), so the maps are meaningless; the time and memory are the real
# model's: UNet 0.87 B, VAE 84 M, CLIP text encoder 0.34 B parameters. Each command runs under
# /usr/bin/time -v (wall time and "Maximum resident set size"); pixl's first load of a checkpoint
# writes the empty-prompt embedding cache beside the weights, so one untimed warm-up per model runs
# first. The diffusers script prints its load time and its pipeline call time separately;
# `pixl estimate normals --json` does the same (load_seconds, estimate_seconds); the table's wall
# time is the whole process (load included) for both.
set -euo pipefail
cd "$(dirname "$0")/.."

THREADS=$(nproc)
PHOTO=""
WEIGHTS=/work/bench-weights
BIN=""
QUICK=""
ONLY=appearance,lighting,normals
RES=512
STEPS=1
while [ $# -gt 0 ]; do
  case "$1" in
    --threads) THREADS=$2; shift 2 ;;
    --photo) PHOTO=$2; shift 2 ;;
    --weights) WEIGHTS=$2; shift 2 ;;
    --bin) BIN=$2; shift 2 ;;
    --quick) QUICK=1; shift ;;
    --steps) STEPS=$2; shift 2 ;;
    --only) ONLY=$2; shift 2 ;;
    --res) RES=$2; shift 2 ;;
    *) echo "unknown argument $1" >&2; exit 2 ;;
  esac
done
KINDS=()
for k in ${ONLY//,/ }; do
  case "$k" in
    appearance|lighting|normals) KINDS+=("$k") ;;
    *) echo "--only: unknown model $k (appearance, lighting, normals)" >&2; exit 2 ;;
  esac
done
[ ${#KINDS[@]} -gt 0 ] || { echo "--only: no model given" >&2; exit 2; }
want() { [[ " ${KINDS[*]} " == *" $1 "* ]]; }
[[ "$RES" =~ ^[0-9]+$ ]] && [ "$RES" -gt 0 ] && [ $((RES % 8)) -eq 0 ] || {
  echo "--res $RES: must be a positive multiple of 8" >&2; exit 2; }
[[ "$STEPS" =~ ^[0-9]+$ ]] && [ "$STEPS" -gt 0 ] || { echo "--steps $STEPS: must be a positive integer" >&2; exit 2; }
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

for kind in "${KINDS[@]}"; do
  if [ ! -f "$WEIGHTS/marigold-$kind/unet/diffusion_pytorch_model.fp16.safetensors" ]; then
    echo "== building random checkpoint $WEIGHTS/marigold-$kind"
    "$PYTHON" scripts/bench/marigold_random_checkpoint.py "$kind" "$WEIGHTS/marigold-$kind"
  fi
done

OUT=$(mktemp -d)
trap 'rm -rf "$OUT"' EXIT

# run LABEL CMD...: one timed run (an executable, not a shell function: /usr/bin/time runs it);
# prints the diffusers script's own timing line or pixl's load / estimate times when the output has
# them, then a table row with the wall time in s and the peak RSS in GB.
run() {
  local label=$1; shift
  /usr/bin/time -v "$@" >"$OUT/log" 2>&1 || { cat "$OUT/log" >&2; echo "$label: FAILED" >&2; return 1; }
  local wall rss load est
  wall=$(awk -F': ' '/Elapsed \(wall clock\)/ {n = split($2, a, ":"); s = 0; for (i = 1; i <= n; i++) s = s * 60 + a[i]; print s}' "$OUT/log")
  rss=$(awk -F': ' '/Maximum resident set size/ {printf "%.2f", $2 / 1024 / 1024}' "$OUT/log")
  grep -E '^diffusers marigold' "$OUT/log" || true
  load=$(grep -o '"load_seconds": *[0-9.e+-]*' "$OUT/log" | grep -o '[0-9.e+-]*$' || true)
  est=$(grep -o '"estimate_seconds": *[0-9.e+-]*' "$OUT/log" | grep -o '[0-9.e+-]*$' || true)
  [ -n "$load" ] && printf 'pixl: load %.1f s, estimate %.2f s\n' "$load" "$est"
  printf '| %s | %s | %s |\n' "$label" "$wall" "$rss"
}

# The estimate subcommand of each model.
declare -A SUBCOMMAND=([appearance]=materials [lighting]=lighting [normals]=normals)

# pixl_cmd KIND RES STEPS: sets PIXL to the command line of one `pixl estimate` run (and removes
# its previous output). materials writes a folder of maps (--force: replace them); lighting and
# normals write one .exr file, and normals prints its load and estimate times (--json).
pixl_cmd() {
  local sub=${SUBCOMMAND[$1]}
  local out=("$OUT/materials" --force)
  [ "$sub" != materials ] && out=("$OUT/$sub.exr")
  rm -f "$OUT/$sub.exr"
  local json=()
  [ "$sub" = normals ] && json=(--json)
  PIXL=(env RAYON_NUM_THREADS="$THREADS" "$BIN" estimate "$sub" "$PHOTO" -o "${out[@]}" --quiet
    --models "$WEIGHTS" --offline --res "$2" --steps "$3" "${json[@]}")
}

echo "machine: $(lscpu | sed -n 's/^Model name: *//p'), $(nproc) cores; threads $THREADS; $(date -u +%F); $BIN"
echo "== warm-up (writes the empty-prompt embedding caches)"
for kind in "${KINDS[@]}"; do
  pixl_cmd "$kind" 64 1
  "${PIXL[@]}" >/dev/null
done

echo "| command | wall s | peak RSS GB |"
echo "|---|---|---|"
for kind in "${KINDS[@]}"; do
  sub=${SUBCOMMAND[$kind]}
  pixl_cmd "$kind" "$RES" "$STEPS"
  run "pixl estimate $sub --res $RES --steps $STEPS" "${PIXL[@]}"
  if [ -z "$QUICK" ]; then
    for rs in "512 4" "768 1" "768 4"; do
      set -- $rs
      pixl_cmd "$kind" "$1" "$2"
      run "pixl estimate $sub --res $1 --steps $2" "${PIXL[@]}"
    done
  fi
done

# side_by_side KIND CLASS: pixl and diffusers on the same photo, resolution and threads (A B A B).
side_by_side() {
  echo "== side by side, $1 $RES px, $STEPS step(s), ensemble 1 (A B A B)"
  for _ in 1 2; do
    pixl_cmd "$1" "$RES" "$STEPS"
    run "pixl estimate ${SUBCOMMAND[$1]} --res $RES --steps $STEPS" "${PIXL[@]}"
    run "diffusers $2 (whole process)" \
      env OMP_NUM_THREADS="$THREADS" "$PYTHON" scripts/bench/marigold_diffusers.py \
      "$WEIGHTS/marigold-$1" "$PHOTO" --res "$RES" --steps "$STEPS" --ensemble 1 --threads "$THREADS"
  done
}
if want appearance; then side_by_side appearance MarigoldIntrinsicsPipeline; fi
if want normals; then side_by_side normals MarigoldNormalsPipeline; fi
