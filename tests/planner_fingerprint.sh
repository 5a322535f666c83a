#!/usr/bin/env bash
# Behaviour fingerprint of the tuned planner for refactors: `build/madbp eval --method madbp
# --json` on seeds 0..N-1 for the 36 interaction cells (6 scenes x 3 maps x 2 / 4 robots) and the
# larger worlds (half-size 2.4: empty and obstacles with 16 and 32 robots; half-size 3.4: 64),
# timing fields removed so two runs compare with `diff`. Any further arguments go to every eval.
#   tests/planner_fingerprint.sh [EPISODES] > before.jsonl   ... change ...   then again and diff.
set -euo pipefail
episodes=${1:-100}
shift || true
tool=${MADBP:-build/madbp}
run() { "$tool" eval --method madbp --episodes "$episodes" --seed 0 --threads "${THREADS:-2}" --json "$@"; }
{
  for scene in swap cross gap corridor parked circle; do
    run --scenario "$scene" --map empty,obstacles,barrier --agents 2,4 "$@"
  done
  run --map empty,obstacles --agents 16,32 --half-size 2.4 --max-steps 200 "$@"
  run --map empty,obstacles --agents 64 --half-size 3.4 --max-steps 200 "$@"
} | sed -E 's/,? *"(plan_ms|decision_ms|wall_s)": *[-0-9.eE+a-z]+//g'
