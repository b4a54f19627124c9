#!/usr/bin/env bash
# `pixl relight PHOTO --depth DEPTH --preset warm-overhead-flash` end to end (reconstruct ->
# lights -> render -> compose -> network -> full-size output), time and peak RSS, for photos of
# the given sizes. The "photos" are the bundled demo scene rendered at each size (its Combined
# pass as an 8-bit PNG, its Depth pass as the depth map), so the run needs no estimator weights.
#
# usage: scripts/bench-relight-photo.sh [--threads T] [--runs N] [WxH ...]   (default 600x400 4000x3000)
set -euo pipefail
cd "$(dirname "$0")/.."
THREADS=$(nproc)
RUNS=3
SIZES=()
while [ $# -gt 0 ]; do
  case "$1" in
    --threads) THREADS=$2; shift 2 ;;
    --runs) RUNS=$2; shift 2 ;;
    *) SIZES+=("$1"); shift ;;
  esac
done
[ ${#SIZES[@]} -eq 0 ] && SIZES=(600x400 4000x3000)
cargo build --release -q -p pixl-cli
PIXL=${CARGO_TARGET_DIR:-target}/release/pixl
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
export RAYON_NUM_THREADS=$THREADS
for size in "${SIZES[@]}"; do
  "$PIXL" render assets/demo/scene.toml --quiet --spp 4 --size "$size" \
    -o "$WORK/in-$size.exr" --preview "$WORK/photo-$size.png"
  for run in $(seq "$RUNS"); do
    rm -f "$WORK/relit-$size.png"
    /usr/bin/time -f "%e s %M KB" -o "$WORK/time" "$PIXL" relight "$WORK/photo-$size.png" \
      --depth "$WORK/in-$size.exr" --fov 50 --preset warm-overhead-flash --quiet -o "$WORK/relit-$size.png"
    echo "$size run $run: $(cat "$WORK/time") (threads $THREADS)"
  done
done
