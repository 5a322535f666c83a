#!/usr/bin/env bash
# Behaviour fingerprint for refactors: `build/madbp eval --json` of every method on the Table I
# cells (seeds 0..N-1), with the timing fields removed so two runs compare with `diff`.
#   tests/eval_fingerprint.sh [EPISODES] > before.jsonl   ... change ...   then again and diff.
set -euo pipefail
episodes=${1:-20}
tool=${MADBP:-build/madbp}
for method in line clfqp expert madbp mappo madiff; do
  for cell in empty:2,4,6 obstacles:2,3,4 barrier:2,3,4; do
    "$tool" eval --method "$method" --map "${cell%%:*}" --agents "${cell#*:}" --episodes "$episodes" \
      --threads 2 --json
  done
done | sed -E 's/,? *"(plan_ms|decision_ms|wall_s)": *[-0-9.eE+a-z]+//g'
