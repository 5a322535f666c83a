#!/usr/bin/env bash
# MA-DBP, the guided expert and the straight line on the MovingAI tuning maps of issue 46
# (maps/movingai/README.md): every map x cell size x team size x seed becomes a scene
# (`madbp convert --movingai`), and every method runs it once (`madbp eval --scene ... --episodes 1`,
# step limit scene_step_limit). One TSV row per episode goes to $OUT; a markdown summary per
# map/cell/n/method is printed (and written next to $OUT as .md).
#
# Scenario rows: seed s with n robots uses rows s*n .. s*n+n-1 counted across the map's scenario
# files in order (<map>-random-1.scen, -random-2, ...; <map>-even-K.scen when there are no random
# ones), never splitting a block of n rows over two files; when the files hold fewer than s+1 blocks
# the blocks are reused (with a warning), so the seeds are then no longer distinct problems.
# A map without scenario files gets n rows drawn from seed s (`madbp convert --random-scen --seed
# s`): start and goal in one component, distinct starts, distinct goals; each seed is its own
# problem.
#
# Settings (environment): MAPS (default: every <map>.map in MAP_DIR), CELLS, AGENTS
# (lists), SEEDS="first last", METHODS, MADBP (the tool), JOBS (episodes in parallel, xargs -P),
# OUT (episode TSV), MAP_DIR (the .map files), SCEN_DIR (the .scen files; default MAP_DIR),
# EVAL_FLAGS (more `madbp eval` flags, all methods), WORK_DIR (scenes and one row file per
# episode, kept after the run; default a temporary folder, removed).
# `scripts/maps_eval.sh --summary [FILE ...]` prints the summary of existing TSVs (below).
set -euo pipefail

MAP_DIR=${MAP_DIR:-maps/movingai}
CELLS=${CELLS:-"0.3 0.25"}
AGENTS=${AGENTS:-"4 8 16 32"}
SEEDS=${SEEDS:-"0 99"}
METHODS=${METHODS:-"madbp expert line"}
MADBP=${MADBP:-build/madbp}
JOBS=${JOBS:-1}
OUT=${OUT:-results/maps/episodes.tsv}
SCEN_DIR=${SCEN_DIR:-$MAP_DIR}
EVAL_FLAGS=${EVAL_FLAGS:-}

HEADER=$'map\tcell\tn\tseed\tmethod\tsuccess\tcollisions\tsteps\tplan_ms'

# Markdown summary of an episode TSV: per map/cell/n/method the episodes k, the success rate p with
# its standard error sqrt(p(1-p)/k), collisions per episode and the mean steps of the successes.
# Rows whose success is not a number (a failed convert or eval) are counted as errors, not episodes.
summary() {
  local file=$1
  echo "| map | cell | n | method | episodes | success | collisions/ep | steps (successes) | errors |"
  echo "| --- | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: |"
  tail -n +2 "$file" | sort -t $'\t' -k1,1 -k2,2gr -k3,3n -k5,5 | awk -F '\t' '
    function flush() {
      if (key == "") return
      if (k > 0) { p = s / k; se = sqrt(p * (1 - p) / k); col = sprintf("%.2f", c / k)
                   rate = sprintf("%.2f +- %.2f", p, se) } else { rate = "-"; col = "-" }
      st = (ns > 0) ? sprintf("%.0f", steps / ns) : "-"
      printf "| %s | %s | %s | %s | %d | %s | %s | %s | %d |\n", m, cell, n, meth, k, rate, col, st, err
    }
    { cur = $1 FS $2 FS $3 FS $5
      if (cur != key) { flush(); key = cur; m = $1; cell = $2; n = $3; meth = $5; k = s = ns = c = steps = err = 0 }
      if ($6 !~ /^[0-9.]+$/) { err++; next }
      k++; s += $6; c += $7; if ($6 > 0) { ns++; steps += $8 } }
    END { flush() }'
}

# `--summary F1 [F2 ...]`: the summary of the files' rows merged, a later file's row replacing an
# earlier one of the same scene (map, cell, n, seed) and method, so a rerun with a newer planner
# is laid over the older run.
if [[ ${1:-} == --summary ]]; then
  shift
  (( $# > 0 )) || set -- "$OUT"
  merged=$(mktemp "${TMPDIR:-/tmp}/maps_eval.XXXXXX")
  trap 'rm -f "$merged"' EXIT
  { echo "$HEADER"
    awk -F '\t' 'FNR > 1 { key = $1 FS $2 FS $3 FS $4 FS $5; if (!(key in row)) order[++k] = key; row[key] = $0 }
                 END { for (i = 1; i <= k; i++) print row[order[i]] }' "$@"; } > "$merged"
  summary "$merged"
  exit 0
fi

if [[ -z ${MAPS:-} ]]; then
  MAPS=$(for f in "$MAP_DIR"/*.map; do [[ -f $f ]] && basename "$f" .map; done | sort | tr '\n' ' ')
  [[ -n $MAPS ]] || { echo "maps_eval: no .map files in $MAP_DIR" >&2; exit 2; }
fi
[[ -x $MADBP ]] || { echo "maps_eval: $MADBP is not an executable (set MADBP=path/to/madbp)" >&2; exit 2; }
read -r SEED_FIRST SEED_LAST <<< "$SEEDS"
SEED_LAST=${SEED_LAST:-$SEED_FIRST}
if [[ -n ${WORK_DIR:-} ]]; then  # kept: an interrupted run's rows stay in $WORK_DIR/rows
  WORK=$WORK_DIR
  rm -rf "$WORK"
else
  WORK=$(mktemp -d "${TMPDIR:-/tmp}/maps_eval.XXXXXX")
  trap 'rm -rf "$WORK"' EXIT
fi
mkdir -p "$WORK/scenes" "$WORK/rows" "$(dirname "$OUT")"

# The scenario files of a map, in order: random ones by number, else even ones.
scen_files() {
  local map=$1 files
  # shellcheck disable=SC2012  # names are <map>-random-K.scen; ls | sort -V orders K numerically
  files=$(ls "$SCEN_DIR/$map"-random-*.scen 2>/dev/null | sort -V || true)
  # shellcheck disable=SC2012
  [[ -n $files ]] || files=$(ls "$SCEN_DIR/$map"-even-*.scen 2>/dev/null | sort -V || true)
  echo "$files"
}

# One scene (map cell n seed, then the convert flags that pick its rows) and its episode jobs, one
# line per method in $WORK/jobs.d/<scene>; a failed convert writes a convert-error row per method
# instead.
convert_scene() {
  local map=$1 cell=$2 n=$3 s=$4 scene method
  shift 4
  scene=$WORK/scenes/$map-c$cell-n$n-s$s.scene
  if ! "$MADBP" convert --movingai "$MAP_DIR/$map.map" "$@" --agents "$n" --cell "$cell" \
       --out "$scene" > /dev/null 2> "$scene.err"; then
    echo "maps_eval: convert failed: $map cell $cell n $n seed $s: $(tail -n 1 "$scene.err")" >&2
    for method in $METHODS; do
      printf '%s\t%s\t%s\t%s\t%s\tconvert-error\t\t\t\n' "$map" "$cell" "$n" "$s" "$method" \
        > "$WORK/rows/$map-c$cell-n$n-s$s-$method.tsv"
    done
    return 0
  fi
  for method in $METHODS; do
    echo "$map $cell $n $s $method $scene"
  done > "$WORK/jobs.d/$map-c$cell-n$n-s$s"
}
# The scenes to make, one line each (convert_scene's arguments), made JOBS at a time below.
plan_scene() { echo "$@" >> "$WORK/converts"; }

# 1. Scenes, JOBS at a time (a large map's convert takes a fraction of a second). Each episode
# job is one line of $WORK/jobs.
mkdir -p "$WORK/jobs.d"
: > "$WORK/converts"
for map in $MAPS; do
  mapfile=$MAP_DIR/$map.map
  [[ -f $mapfile ]] || { echo "maps_eval: no map file $mapfile" >&2; exit 2; }
  scens=$(scen_files "$map")
  if [[ -z $scens ]]; then
    echo "maps_eval: $map: no scenario files $SCEN_DIR/$map-random-*.scen or -even-*.scen; rows drawn per seed (--random-scen)" >&2
  fi
  for n in $AGENTS; do
    if [[ -z $scens ]]; then  # rows drawn from the episode's seed
      for cell in $CELLS; do
        for (( s = SEED_FIRST; s <= SEED_LAST; s++ )); do
          plan_scene "$map" "$cell" "$n" "$s" --random-scen --seed "$s"
        done
      done
      continue
    fi
    # Blocks of n rows per file, in file order.
    files=(); blocks=(); total=0
    for f in $scens; do
      rows=$(( $(grep -c . "$f") - 1 ))
      files+=("$f"); blocks+=($(( rows / n ))); total=$(( total + rows / n ))
    done
    (( total > 0 )) || { echo "maps_eval: $map: fewer than $n scenario rows in every file" >&2; exit 2; }
    (( SEED_LAST < total )) || echo "maps_eval: $map n=$n: $total blocks of $n rows for seeds $SEED_FIRST..$SEED_LAST; blocks are reused" >&2
    for cell in $CELLS; do
      for (( s = SEED_FIRST; s <= SEED_LAST; s++ )); do
        b=$(( s % total )); i=0
        while (( b >= blocks[i] )); do b=$(( b - blocks[i] )); i=$(( i + 1 )); done
        plan_scene "$map" "$cell" "$n" "$s" --scen "${files[i]}" --offset $(( b * n ))
      done
    done
  done
done

export -f convert_scene
export MADBP MAP_DIR METHODS WORK
xargs -P "$JOBS" -L 1 bash -c 'convert_scene "$@"' _ < "$WORK/converts"
cat "$WORK/jobs.d/"* > "$WORK/jobs" 2> /dev/null || true

# 2. Episodes, JOBS at a time, seed by seed and within a seed larger teams first (they take
# longest: the run then ends with short episodes, and a run cut short has whole seeds); each
# writes one row file (a failed eval writes an eval-error row).
run_one() {
  local map=$1 cell=$2 n=$3 s=$4 method=$5 scene=$6 json success collisions steps plan_ms
  # shellcheck disable=SC2086  # EVAL_FLAGS is a list of flags
  if json=$("$MADBP" eval --method "$method" --scene "$scene" --episodes 1 --seed "$s" --json $EVAL_FLAGS 2> "$scene.$method.err"); then
    field() { grep -o "\"$1\": [^,}]*" <<< "$json" | head -n 1 | sed 's/.*: //'; }
    success=$(field success); collisions=$(field collisions); steps=$(field steps); plan_ms=$(field plan_ms)
    [[ $steps == null ]] && steps=
  else
    echo "maps_eval: eval failed: $map cell $cell n $n seed $s $method: $(tail -n 1 "$scene.$method.err")" >&2
    success=eval-error; collisions=; steps=; plan_ms=
  fi
  printf '%s\t%s\t%s\t%s\t%s\t%s\t%s\t%s\t%s\n' "$map" "$cell" "$n" "$s" "$method" \
    "$success" "$collisions" "$steps" "$plan_ms" > "$WORK/rows/$map-c$cell-n$n-s$s-$method.tsv"
}
export -f run_one
export MADBP EVAL_FLAGS WORK
njobs=$(wc -l < "$WORK/jobs")
echo "maps_eval: $njobs episodes, $JOBS at a time" >&2
if (( njobs > 0 )); then
  sort -s -k4,4n -k3,3nr "$WORK/jobs" | xargs -P "$JOBS" -L 1 bash -c 'run_one "$@"' _
fi

# 3. The episode table (sorted like the summary) and the summary.
{ echo "$HEADER"; cat "$WORK/rows/"*.tsv | sort -t $'\t' -k1,1 -k2,2gr -k3,3n -k4,4n -k5,5; } > "$OUT.tmp"
mv "$OUT.tmp" "$OUT"
summary "$OUT" | tee "${OUT%.tsv}.md"
