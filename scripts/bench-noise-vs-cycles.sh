#!/usr/bin/env bash
# Noise benchmark of the native renderer against Blender Cycles (BENCHMARKS.md, "Native renderer
# noise vs Blender Cycles"): for the demo scene and the 500 k-triangle depth-mesh scene of `bench_render`,
# each renderer's own high-spp reference, then renders at a few spp, and per pass the RMSE against
# the renderer's own reference, the path-tracing time and the error per second 1 / (RMSE² · t).
#
# usage: scripts/bench-noise-vs-cycles.sh OUT_DIR
# environment (defaults in brackets):
#   PIXL          pixl binary, for `pixl blender export` [target/release/pixl]
#   BPY_PYTHON    Python 3.11 with PyPI bpy==5.0.1 [/work/bpyenv/bin/python]
#   RUN_CYCLES    run_cycles.py of the shared tools [../shared/tools/run_cycles.py]
#   NOISE_RMSE    the noise_rmse example [built here into $CARGO_TARGET_DIR or target/]
#   OLD_NOISE_RMSE  optional: noise_rmse built from older code, measured as "ours-old" against
#                 the same reference (its `render` must take SEED REPEAT)
#   DEMO_W, MESH_W  render widths of the demo (aspect 160:128) and mesh (square) scenes [256, 256]
#   REF_SPP       spp of the references [1024]
#   SPPS          spp of the measured renders ["1 4 16 64"]
#   THREADS       threads for both renderers [2]
#   SCENES        which scenes ["demo mesh"]
#   REPEAT        renders per measurement, the median time kept (same image each time) [3]
# References already in OUT_DIR are reused (delete them to remake); SUMMARY_ONLY=1 only remakes the
# summary from OUT_DIR/results.tsv. Results: OUT_DIR/results.tsv
# (scene renderer spp pass rmse seconds test_mean ref_mean under_half: the share of lit pixels
# under half their reference value) and OUT_DIR/summary.md.
set -euo pipefail
out=${1:?usage: bench-noise-vs-cycles.sh OUT_DIR}
root=$(cd "$(dirname "$0")/.." && pwd)
mkdir -p "$out"
out=$(cd "$out" && pwd)
PIXL=${PIXL:-$root/target/release/pixl}
BPY_PYTHON=${BPY_PYTHON:-/work/bpyenv/bin/python}
RUN_CYCLES=${RUN_CYCLES:-$root/../shared/tools/run_cycles.py}
DEMO_W=${DEMO_W:-256}
MESH_W=${MESH_W:-256}
REF_SPP=${REF_SPP:-1024}
SPPS=${SPPS:-"1 4 16 64"}
THREADS=${THREADS:-2}
SCENES=${SCENES:-"demo mesh"}
REPEAT=${REPEAT:-3}
export RAYON_NUM_THREADS=$THREADS
target=${CARGO_TARGET_DIR:-$root/target}
if [ -z "${NOISE_RMSE:-}" ]; then
    (cd "$root" && cargo build --release --locked -p pixl-render --example noise_rmse --example bench_render)
    NOISE_RMSE=$target/release/examples/noise_rmse
fi
BENCH_RENDER=${BENCH_RENDER:-$target/release/examples/bench_render}

# Scenes at the chosen sizes, and their Cycles scripts.
for s in $SCENES; do
    mkdir -p "$out/$s"
    if [ ! -f "$out/$s/scene.py" ]; then
        case $s in
        demo)
            h=$(( (DEMO_W * 128 + 80) / 160 ))
            sed -e "s/^width = 160/width = $DEMO_W/" -e "s/^height = 128/height = $h/" \
                "$root/assets/demo/scene.toml" > "$out/demo/scene.toml" ;;
        mesh)
            PIXL_BENCH_SAVE="$out/mesh" "$BENCH_RENDER" 500 1 render-only 1 > /dev/null
            sed -i -e "s/^width = 512/width = $MESH_W/" -e "s/^height = 512/height = $MESH_W/" "$out/mesh/scene.toml" ;;
        *) echo "unknown scene $s" >&2; exit 2 ;;
        esac
        "$PIXL" blender export "$out/$s/scene.toml" -o "$out/$s/scene.py" -q
    fi
done

ours() { # scene spp exr seed repeat [binary] -> prints the median seconds
    "${6:-$NOISE_RMSE}" render "$out/$1/scene.toml" "$2" "$3" "$4" "$5" | awk '/^RENDER_S/ {print $2}'
}
cycles() { # scene spp exr seed repeat -> prints the median path_trace seconds
    for _ in $(seq "$5"); do
        "$BPY_PYTHON" "$RUN_CYCLES" "$out/$1/scene.py" --out "$3" --spp "$2" --threads "$THREADS" --seed "$4" 2>&1 \
            | sed -n 's/^CYCTIME //p' | python3 -c 'import json,sys; print(json.load(sys.stdin)["path_trace"])'
    done | sort -g | awk '{t[NR] = $1} END {print t[int((NR + 1) / 2)]}'
}

# References (seed 1; the measured renders use seed 0, so they share no samples with them).
[ -n "${SUMMARY_ONLY:-}" ] || for s in $SCENES; do
    [ -f "$out/$s/ref_ours.exr" ] || { t=$(ours "$s" "$REF_SPP" "$out/$s/ref_ours.exr" 1 1); echo "$s ours reference $REF_SPP spp: $t s"; }
    [ -f "$out/$s/ref_cycles.exr" ] || { t=$(cycles "$s" "$REF_SPP" "$out/$s/ref_cycles.exr" 1 1); echo "$s Cycles reference $REF_SPP spp: $t s"; }
    "$NOISE_RMSE" rmse "$out/$s/ref_cycles.exr" "$out/$s/ref_ours.exr" | sed "s/^RMSE /$s /" > "$out/$s/ref_means.txt"
done

# Measured renders, the renderers alternated per spp (SUMMARY_ONLY=1: only remake the summary).
res=$out/results.tsv
[ -n "${SUMMARY_ONLY:-}" ] || : > "$res"
[ -n "${SUMMARY_ONLY:-}" ] || for s in $SCENES; do
    for spp in $SPPS; do
        runs="ours cycles"
        [ -n "${OLD_NOISE_RMSE:-}" ] && runs="ours-old $runs"
        for r in $runs; do
            exr=$out/$s/$r-$spp.exr
            case $r in
            ours) t=$(ours "$s" "$spp" "$exr" 0 "$REPEAT"); ref=$out/$s/ref_ours.exr ;;
            ours-old) t=$(ours "$s" "$spp" "$exr" 0 "$REPEAT" "$OLD_NOISE_RMSE"); ref=$out/$s/ref_ours.exr ;;
            cycles) t=$(cycles "$s" "$spp" "$exr" 0 "$REPEAT"); ref=$out/$s/ref_cycles.exr ;;
            esac
            echo "$s $r $spp spp: $t s"
            "$NOISE_RMSE" rmse "$ref" "$exr" | awk -v s="$s" -v r="$r" -v n="$spp" -v t="$t" \
                '/^RMSE/ {print s "\t" r "\t" n "\t" $2 "\t" $3 "\t" t "\t" $4 "\t" $5 "\t" $6}' >> "$res"
        done
    done
done

python3 - "$out" "$REF_SPP" <<'EOF' | tee "$out/summary.md"
import sys, collections
out, ref_spp = sys.argv[1], sys.argv[2]
rows = [l.rstrip("\n").split("\t") for l in open(f"{out}/results.tsv") if l.strip()]
by = collections.defaultdict(dict)
times = {}
half = {}
for scene, r, spp, p, rmse, t, tm, rm, h in rows:
    by[(scene, int(spp), p)][r] = (float(rmse), float(t), float(rm))
    times[(scene, r, int(spp))] = float(t)
    half[(scene, r, int(spp), p)] = float(h)
scenes = sorted({k[0] for k in by}, key=["demo", "mesh"].index)
for scene in scenes:
    print(f"\n**{scene}**: path-tracing time (s) per spp: " + "; ".join(
        f"{spp} spp " + ", ".join(f"{r} {times[(scene, r, spp)]:.2f}" for r in ("ours-old", "ours", "cycles") if (scene, r, spp) in times)
        for spp in sorted({k[2] for k in times if k[0] == scene})))
    means = {}
    for l in open(f"{out}/{scene}/ref_means.txt"):
        _, p, _, om, cm = l.split()[:5]
        means[p] = (float(om), float(cm))
    has_old = any("ours-old" in v for k, v in by.items() if k[0] == scene)
    head = "| pass | ours / Cycles ref. mean (rel. diff) | spp | " + ("ours-old | " if has_old else "") + "ours | Cycles | ours / Cycles |"
    print("\n" + head)
    print("|" + "---|" * (head.count("|") - 1))
    for (sc, spp, p), v in sorted(by.items(), key=lambda kv: (kv[0][2] != "Combined", kv[0][2], kv[0][1])):
        if sc != scene or "ours" not in v or "cycles" not in v:
            continue
        om, cm = means.get(p, (0.0, 0.0))
        if max(abs(om), abs(cm)) < 1e-6:
            continue  # an empty pass
        eps = {r: (1.0 / (x[0] ** 2 * x[1]) if x[0] > 0 else float("inf")) for r, x in v.items()}
        rel = f"{100 * (om - cm) / cm:+.2f} %" if cm else "–"
        cells = ([f"{eps['ours-old']:.3g}"] if has_old else []) + [f"{eps['ours']:.3g}", f"{eps['cycles']:.3g}", f"{eps['ours'] / eps['cycles']:.2f}"]
        print(f"| {p} | {om:.5f} / {cm:.5f} ({rel}) | {spp} | " + " | ".join(cells) + " |")
for scene in scenes:
    for spp in sorted({k[2] for k in half if k[0] == scene}):
        print(f"\n{scene}, {spp} spp: share of lit pixels with less than half their reference Diffuse Direct: " + ", ".join(
            f"{r} {100 * half[(scene, r, spp, 'DiffDir')]:.2f} %" for r in ("ours-old", "ours", "cycles") if (scene, r, spp, "DiffDir") in half))
print(f"\nerror per second = 1 / (RMSE² · path-tracing seconds), RMSE against each renderer's own {ref_spp}-spp reference.")
EOF
