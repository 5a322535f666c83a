#!/usr/bin/env bash
# Merges the result directories of suite shards (scripts/slurm-results.sh, or any runs of
# `madbp eval --suite paper --shard i/N --out DIR`) into one directory and re-renders every report
# there (docs/packaging.md "Cluster sweeps").
#
#   scripts/merge-results.sh [--allow-run] OUT SHARD_DIR... [-- SUITE_OPTIONS...]
#
# 1. OUT/cells.tsv := OUT's own lines (if any), then each shard's, in the order given, exact
#    duplicates dropped. The store's rules do the rest: later lines override earlier ones of the
#    same id, and a torn line (a shard killed mid-write) stays ignored.
# 2. The files cells write besides their line (episode-*.svg, fig3a/'s models and datasets) are
#    copied from every shard (reports are copied too, then regenerated). Steps 1-3 work in
#    OUT.merging/ and only then replace OUT's files: a refused merge leaves OUT as it was.
# 3. `madbp eval --suite paper --out OUT SUITE_OPTIONS --list` must show no cell to do: a cell
#    that is neither done nor missing (a shard failed or was not run) stops the merge with the
#    list, unless --allow-run (then step 4 runs those cells here).
# 4. `madbp eval --suite paper --out OUT SUITE_OPTIONS`: every cell is done, so it runs nothing
#    and only regenerates OUT/*.md, *.csv, *.svg and index.md from the merged store. Its last line
#    is "suite: 0 cells run, ...".
# SUITE_OPTIONS: the shards' --only / --models / --episodes, if they were given any (not --shard,
# --out or --threads). MADBP names the tool (default build/madbp).
set -euo pipefail
madbp=${MADBP:-build/madbp}
allow_run=0
if [ "${1:-}" = --allow-run ]; then allow_run=1; shift; fi
if [ $# -lt 2 ]; then sed -n '2,/^set -e/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 2; fi
out=${1%/}; shift
shards=()
while [ $# -gt 0 ] && [ "$1" != -- ]; do shards+=("${1%/}"); shift; done
[ "${1:-}" = -- ] && shift
options=("$@")
[ ${#shards[@]} -gt 0 ] || { echo "merge-results: no shard directories given" >&2; exit 2; }
for s in "${shards[@]}"; do
  [ -f "$s/cells.tsv" ] || { echo "merge-results: $s/cells.tsv does not exist" >&2; exit 2; }
  [ "$(cd "$s" && pwd -P)" != "$(mkdir -p "$out" && cd "$out" && pwd -P)" ] ||
    { echo "merge-results: $s is OUT itself" >&2; exit 2; }
done

# Built in a staging directory first, so that a refused merge leaves OUT as it was.
stage=$out.merging
rm -rf "$stage" && mkdir -p "$stage" "$out"
cp -rp "$out/." "$stage/"
stores=()
[ -f "$out/cells.tsv" ] && stores+=("$out/cells.tsv")
for s in "${shards[@]}"; do
  cp -rp "$s/." "$stage/"  # episode pictures, fig3a/; the store and the reports are rewritten below
  stores+=("$s/cells.tsv")
done
# awk ends every line with a newline, so a torn last line cannot swallow the next file's first.
awk '!seen[$0]++' "${stores[@]}" > "$stage/cells.tsv"
echo "merge-results: $(grep -c . "$stage/cells.tsv") store lines from ${#shards[@]} shards"

todo=$("$madbp" eval --suite paper --out "$stage" "${options[@]}" --list | awk '$3 != "done" && $3 != "missing"')
if [ -n "$todo" ]; then
  echo "merge-results: $(grep -c . <<<"$todo") cells are not done in the merged store:"
  head -n 20 <<<"$todo"
  if [ $allow_run = 0 ]; then
    rm -rf "$stage"
    echo "merge-results: $out left as it was; rerun those shards (the store resumes), or pass --allow-run to run them here" >&2
    exit 1
  fi
fi
cp -rp "$stage/." "$out/" && rm -rf "$stage"
"$madbp" eval --suite paper --out "$out" "${options[@]}"
