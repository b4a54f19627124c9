#!/usr/bin/env bash
# `pixl relight CLIP --static --depth DEPTH --preset … -o OUT.mp4` on a 10 s 720p clip: wall time,
# frames per second and peak RSS. The clip is the bundled demo scene rendered at 1280x720 (its
# Depth pass is the depth map) looped for 10 s at 30 fps with a slowly changing brightness, H.264.
#
# usage: scripts/bench-video.sh [--threads T] [SECONDS]      (default 10)
set -euo pipefail
cd "$(dirname "$0")/.."
THREADS=$(nproc)
if [ "${1:-}" = "--threads" ]; then THREADS=$2; shift 2; fi
SECS=${1:-10}
cargo build --release -q -p pixl-cli
PIXL=$(pwd)/${CARGO_TARGET_DIR:-target}/release/pixl
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
export RAYON_NUM_THREADS=$THREADS
"$PIXL" render assets/demo/scene.toml --quiet --spp 16 --size 1280x720 -o "$WORK/in.exr" --preview "$WORK/photo.png"
ffmpeg -v error -loop 1 -i "$WORK/photo.png" -t "$SECS" -r 30 -vf "eq=brightness=0.04*sin(2*PI*t/5)" \
  -c:v libx264 -pix_fmt yuv420p "$WORK/clip.mp4"
/usr/bin/time -f "%e %M %P" -o "$WORK/time" "$PIXL" relight "$WORK/clip.mp4" --static --depth "$WORK/in.exr" \
  --fov 50 --preset warm-overhead-flash --quiet -o "$WORK/relit.mp4"
read -r secs kb cpu < "$WORK/time"
frames=$(ffprobe -v error -count_frames -select_streams v:0 -show_entries stream=nb_read_frames -of csv=p=0 "$WORK/relit.mp4")
awk -v s="$secs" -v k="$kb" -v f="$frames" -v c="$cpu" -v t="$THREADS" \
  'BEGIN { printf "%d frames of 1280x720: %.1f s, %.2f frames/s, peak RSS %.0f MiB, CPU %s (threads %d)\n", f, s, f / s, k / 1024, c, t }'
