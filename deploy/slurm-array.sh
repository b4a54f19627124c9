#!/usr/bin/env bash
# A Slurm job array that relights a folder of photos in 8 shards: each task runs
# `pixl relight --shard auto`, which reads its index from SLURM_ARRAY_TASK_ID (less
# SLURM_ARRAY_TASK_MIN) and the count from SLURM_ARRAY_TASK_COUNT. Resubmitting the array after a
# failure or a preemption relights only the photos not yet done (the logs in the output folder).
#
#   sbatch deploy/slurm-array.sh /shared/shots /shared/depths /shared/relit
#SBATCH --job-name=pixl-relight
#SBATCH --array=0-7
#SBATCH --cpus-per-task=4
#SBATCH --mem=12G
#SBATCH --time=04:00:00
#SBATCH --output=pixl-relight-%A_%a.log
set -euo pipefail
SHOTS="${1:?usage: sbatch slurm-array.sh SHOTS_DIR DEPTH_DIR OUT_DIR}"
DEPTHS="${2:?usage: sbatch slurm-array.sh SHOTS_DIR DEPTH_DIR OUT_DIR}"
OUT="${3:?usage: sbatch slurm-array.sh SHOTS_DIR DEPTH_DIR OUT_DIR}"
export RAYON_NUM_THREADS="${SLURM_CPUS_PER_TASK:-4}"
# PIXL_MODELS_DIR: a shared folder holding the models (`pixl models fetch ... --models DIR`).
exec pixl relight "$SHOTS" --depth-dir "$DEPTHS" --preset cool-side-flash --shard auto -o "$OUT"
