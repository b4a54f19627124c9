#!/usr/bin/env bash
# Two real public-domain photographs relit under the paper's five presets, with hand-made depth:
# scikit-image's `chelsea.png` (a cat's face, 451x300, CC0) and `rocket.jpg` (a launch pad at dusk,
# 640x427, public domain, NASA), both taken from the scikit-image wheel on PyPI. Per photo and per
# weights file: the five relit images, the light-response score against the path-traced renders of
# the same reconstruction (pixl-eval's `light_response`), and one contact sheet
# (source | the five presets, relit; the five path-traced renders below).
#
#   scripts/real-photos.sh OUT [--weights W]... [--spp N]
#
#   OUT         output folder (created; photos, depths, OUT/<weights name>/<photo>/<preset>.png,
#               OUT/<weights name>/<photo>/sheet.png, OUT/summary.tsv)
#   --weights   `bundled` (default) or a .safetensors file; repeat to compare several
#   --spp       path-tracing samples per pixel of the renders (default 64)
#
# Depths are hand-made (no estimator weights are needed), metric, in metres, written as .npy:
#   chelsea: a background plane at 2.0 m behind the head, an ellipsoid (the head) centred at
#            (0.52 w, 0.55 h), semi-axes 0.48 w by 0.62 h, 1.0 m at its nearest point;
#   rocket:  the sky a plane at 60 m, the rocket and the four towers (columns marked by hand)
#            a plane at 40 m, the ground below 0.9 h rising from 40 m to 25 m at the bottom row.
# Needs python3 with a venv (numpy and pillow are installed into $PIXL_PHOTOS_VENV, default
# $HOME/.cache/pixl/venv-photos) and builds `pixl` in release mode unless PIXL_BIN is set.
set -euo pipefail
cd "$(dirname "$0")/.."

usage() { sed -n '2,23p' "$0" | sed 's/^# \{0,1\}//'; }
OUT=""
WEIGHTS=()
SPP=64
while [ $# -gt 0 ]; do
  case "$1" in
    --weights) WEIGHTS+=("$2"); shift 2 ;;
    --spp) SPP=$2; shift 2 ;;
    -h | --help) usage; exit 0 ;;
    -*) echo "unknown option $1" >&2; usage >&2; exit 2 ;;
    *) if [ -n "$OUT" ]; then echo "one OUT folder only" >&2; exit 2; fi; OUT=$1; shift ;;
  esac
done
[ -n "$OUT" ] || { usage >&2; exit 2; }
[ ${#WEIGHTS[@]} -gt 0 ] || WEIGHTS=(bundled)
for w in "${WEIGHTS[@]}"; do
  if [ "$w" != bundled ] && [ ! -f "$w" ]; then echo "weights file $w not found" >&2; exit 2; fi
done
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)

VENV=${PIXL_PHOTOS_VENV:-$HOME/.cache/pixl/venv-photos}
if [ ! -x "$VENV/bin/python" ]; then python3 -m venv "$VENV"; fi
PY=$VENV/bin/python
"$PY" -c "import numpy, PIL" 2>/dev/null || "$PY" -m pip install -q numpy pillow

if [ -z "${PIXL_BIN:-}" ]; then
  cargo build --release -q -p pixl-cli
  PIXL_BIN=${CARGO_TARGET_DIR:-target}/release/pixl
fi
cargo build --release -q -p pixl-eval --example light_response
RESPONSE=${CARGO_TARGET_DIR:-target}/release/examples/light_response

# The photographs, from the scikit-image wheel (nothing else of it is installed).
if [ ! -f "$OUT/chelsea.png" ] || [ ! -f "$OUT/rocket.png" ]; then
  WHEELS=$(mktemp -d)
  "$PY" -m pip download -q --no-deps scikit-image==0.26.0 -d "$WHEELS"
  "$PY" - "$WHEELS" "$OUT" <<'EOF'
import glob, io, sys, zipfile
from PIL import Image
wheels, out = sys.argv[1], sys.argv[2]
z = zipfile.ZipFile(glob.glob(f"{wheels}/scikit_image-*.whl")[0])
for name in ("chelsea.png", "rocket.jpg"):
    img = Image.open(io.BytesIO(z.read(f"skimage/data/{name}"))).convert("RGB")
    img.save(f"{out}/{name.split('.')[0]}.png")
EOF
  rm -rf "$WHEELS"
fi

"$PY" - "$OUT" <<'EOF'
import sys
import numpy as np
from PIL import Image
out = sys.argv[1]
def grid(name):
    w, h = Image.open(f"{out}/{name}.png").size
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return (x + 0.5) / w, (y + 0.5) / h
# chelsea: the head an ellipsoid in front of a background plane.
u, v = grid("chelsea")
r2 = ((u - 0.52) / 0.48) ** 2 + ((v - 0.55) / 0.62) ** 2
depth = np.where(r2 < 1.0, 1.0 + 0.6 * (1.0 - np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))), 2.0)
np.save(f"{out}/chelsea_depth.npy", np.minimum(depth, 2.0).astype(np.float32))
# rocket: sky, structures, ground.
u, v = grid("rocket")
depth = np.full(u.shape, 60.0)
for lo, hi, top in ((0.0, 0.14, 0.0), (0.27, 0.33, 0.29), (0.47, 0.53, 0.29), (0.68, 0.74, 0.29), (0.87, 1.0, 0.0)):
    depth[(u >= lo) & (u < hi) & (v >= top)] = 40.0
ground = v >= 0.9
depth[ground] = 40.0 - 15.0 * (v[ground] - 0.9) / 0.1
np.save(f"{out}/rocket_depth.npy", depth.astype(np.float32))
EOF

PRESETS=(cool-side-flash warm-overhead-flash dim-overhead-spot soft-frontal-sun warm-interior-sun)
printf 'weights\tphoto\tgain\tcorrelation\n' > "$OUT/summary.tsv"
for w in "${WEIGHTS[@]}"; do
  tag=$(basename "$w" .safetensors)
  for photo in chelsea rocket; do
    dir=$OUT/$tag/$photo
    mkdir -p "$dir"
    pairs=()
    for p in "${PRESETS[@]}"; do
      echo "== $tag $photo $p" >&2
      rm -rf "$dir/$p-steps"
      "$PIXL_BIN" relight "$OUT/$photo.png" --depth "$OUT/${photo}_depth.npy" --depth-kind metric \
        --preset "$p" --weights "$w" --spp "$SPP" -o "$dir/$p.png" --keep "$dir/$p-steps" -q
      cp "$dir/$p-steps/render.png" "$dir/$p-render.png"
      pairs+=("$dir/$p.png" "$dir/$p-render.png")
    done
    score=$("$RESPONSE" "${pairs[@]}")
    echo "$tag $photo $score" >&2
    printf '%s\t%s\t%s\t%s\n' "$tag" "$photo" \
      "$("$PY" -c 'import json,sys; print(json.loads(sys.argv[1])["gain"])' "$score")" \
      "$("$PY" -c 'import json,sys; print(json.loads(sys.argv[1])["correlation"])' "$score")" >> "$OUT/summary.tsv"
    "$PY" - "$OUT/$photo.png" "$dir" "${PRESETS[@]}" <<'EOF'
import sys
from PIL import Image, ImageDraw
src, d, presets = sys.argv[1], sys.argv[2], sys.argv[3:]
s = Image.open(src).convert("RGB")
w, h = s.size
scale = 240 / max(w, h)
tw, th = round(w * scale), round(h * scale)
sheet = Image.new("RGB", ((len(presets) + 1) * tw, 2 * (th + 16)), "white")
draw = ImageDraw.Draw(sheet)
def put(img, col, row, label):
    sheet.paste(img.convert("RGB").resize((tw, th), Image.LANCZOS), (col * tw, row * (th + 16) + 16))
    draw.text((col * tw + 4, row * (th + 16) + 2), label, fill="black")
put(s, 0, 0, "source")
for i, p in enumerate(presets):
    put(Image.open(f"{d}/{p}.png"), i + 1, 0, f"relit: {p}")
    put(Image.open(f"{d}/{p}-render.png"), i + 1, 1, "path-traced render")
sheet.save(f"{d}/sheet.png")
EOF
  done
done
column -t "$OUT/summary.tsv"
