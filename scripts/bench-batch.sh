#!/usr/bin/env bash
# Many photos: one `pixl relight FOLDER --depth-dir DEPTHS -o OUT` (models loaded once, the next
# photo decoded while the network runs) against one `pixl relight PHOTO --depth DEPTH -o OUT` per
# photo, same photos, same machine, same run: wall time, photos per minute and peak RSS of each.
# The photos are the bundled demo scene rendered at SIZE (its Combined pass as an 8-bit PNG, its
# Depth pass as the depth map), N copies, so no estimator weights are needed.
#
# usage: scripts/bench-batch.sh [--threads T] [N] [WxH]      (default 50 600x400)
set -euo pipefail
cd "$(dirname "$0")/.."
THREADS=$(nproc)
if [ "${1:-}" = "--threads" ]; then THREADS=$2; shift 2; fi
N=${1:-50}
SIZE=${2:-600x400}
cargo build --release -q -p pixl-cli
PIXL=$(pwd)/${CARGO_TARGET_DIR:-target}/release/pixl
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
export RAYON_NUM_THREADS=$THREADS
mkdir -p "$WORK/shots" "$WORK/depths" "$WORK/separate"
"$PIXL" render assets/demo/scene.toml --quiet --spp 4 --size "$SIZE" -o "$WORK/in.exr" --preview "$WORK/photo.png"
for i in $(seq -w 1 "$N"); do
  cp "$WORK/photo.png" "$WORK/shots/p$i.png"
  cp "$WORK/in.exr" "$WORK/depths/p$i.exr"
done
FLAGS=(--fov 50 --preset warm-overhead-flash --quiet)
/usr/bin/time -f "%e %M" -o "$WORK/batch.time" \
  "$PIXL" relight "$WORK/shots" --depth-dir "$WORK/depths" "${FLAGS[@]}" -o "$WORK/batch"
/usr/bin/time -f "%e %M" -o "$WORK/separate.time" bash -c '
  PIXL=$1; WORK=$2; shift 2
  for f in "$WORK"/shots/*.png; do
    n=$(basename "$f" .png)
    "$PIXL" relight "$f" --depth "$WORK/depths/$n.exr" "$@" -o "$WORK/separate/$n.png"
  done' _ "$PIXL" "$WORK" "${FLAGS[@]}"
report() {
  read -r secs kb < "$WORK/$1.time"
  awk -v w="$1" -v s="$secs" -v k="$kb" -v n="$N" -v size="$SIZE" -v t="$THREADS" \
    'BEGIN { printf "%-8s %d photos of %s: %.1f s, %.1f photos/min, peak RSS %.0f MiB (threads %d)\n", w, n, size, s, n * 60 / s, k / 1024, t }'
}
report batch
report separate
cmp -s "$WORK/batch/p$(seq -w 1 "$N" | head -1).png" "$WORK/separate/p$(seq -w 1 "$N" | head -1).png" \
  && echo "outputs: the same bytes" || echo "outputs: differ"
