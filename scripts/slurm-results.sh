#!/usr/bin/env bash
# Slurm array job: each task runs one shard of `madbp eval --suite paper` into its own directory,
# results-shards/<i>/ (docs/packaging.md "Cluster sweeps"). Then merge them into results/:
#   make build/madbp ARCH=              # on a login node; ARCH= unless every node has its CPU
#   mkdir -p logs && sbatch scripts/slurm-results.sh            # 16 shards (--array below)
#   sbatch --array=0-31 scripts/slurm-results.sh                # or any other count
#   scripts/merge-results.sh results results-shards/*           # after the last task
# A shard that fails or times out resumes where it stopped when its task is resubmitted
# (sbatch --array=<i> ...): the suite skips the cells its store has as done.
# Environment: MADBP (tool, default build/madbp), MADBP_SHARD_DIR (default results-shards),
# MADBP_SUITE_FLAGS (more suite options, e.g. "--episodes 20 --only table1,fig4").
#SBATCH --job-name=madbp-results
#SBATCH --array=0-15
#SBATCH --cpus-per-task=2
#SBATCH --mem=4G
#SBATCH --time=12:00:00
#SBATCH --output=logs/madbp-results-%A_%a.out
set -euo pipefail
cd "${SLURM_SUBMIT_DIR:-.}"
: "${SLURM_ARRAY_TASK_ID:?run this as a Slurm array task (sbatch scripts/slurm-results.sh)}"
min=${SLURM_ARRAY_TASK_MIN:-0}
count=${SLURM_ARRAY_TASK_COUNT:-$((SLURM_ARRAY_TASK_MAX - min + 1))}
shard=$((SLURM_ARRAY_TASK_ID - min))
out=${MADBP_SHARD_DIR:-results-shards}/$shard
export OMP_WAIT_POLICY=${OMP_WAIT_POLICY:-passive}
echo "madbp-results: shard $shard/$count on $(hostname) into $out"
# shellcheck disable=SC2086  # MADBP_SUITE_FLAGS is a list of options
exec "${MADBP:-build/madbp}" eval --suite paper --threads "${SLURM_CPUS_PER_TASK:-2}" --shard "$shard/$count" \
  --out "$out" ${MADBP_SUITE_FLAGS:-}
