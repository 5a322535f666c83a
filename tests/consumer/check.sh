#!/usr/bin/env bash
# Packaging checks (docs/packaging.md; `make test-consumer`; .ci/run). Each check prints one line
# "ok: ..." or "FAILED: ..." (with its log's tail); the last line is "N passed, N failed".
#   1. install   cmake configure + `cmake --install` into a temporary prefix: headers, model,
#                CMake config and version files, madbp.pc, the tool (built by CMake)
#   2. tool      the installed bin/madbp runs `demo` from another directory with the installed
#                model, also after the prefix is moved; MADBP_MODEL overrides it
#   3. cmake     tests/consumer/cmake: find_package(madbp CONFIG REQUIRED), builds, plans with the
#                installed model
#   4. pkgconfig tests/consumer/pkgconfig: the same program from a plain Makefile and madbp.pc
#   5. fetch     tests/consumer/fetchcontent: FetchContent (add_subdirectory) of this checkout
#   6. python    examples/python: numpy's Linear layer and dataset reader against the C++ library
#   7. shards    scripts/slurm-results.sh (as two array tasks) and scripts/merge-results.sh on a
#                tiny suite: the merge runs no cell and reproduces an unsharded run's results
# Needs build/madbp (make builds it first) and installs cmake, pkg-config and python3-numpy
# through apt when missing. KEEP=1 keeps the temporary directory.
set -uo pipefail
cd "$(dirname "$0")/../.."
root=$PWD
madbp=$root/${MADBP:-build/madbp}
export OMP_WAIT_POLICY=${OMP_WAIT_POLICY:-passive}
python=/usr/bin/python3  # Debian's, where python3-numpy installs numpy
export PYTHONDONTWRITEBYTECODE=1  # no __pycache__ in the checkout

need=()
command -v cmake >/dev/null || need+=(cmake)
command -v pkg-config >/dev/null || need+=(pkg-config)
"$python" -c 'import numpy' 2>/dev/null || need+=(python3-numpy)
if [ ${#need[@]} -gt 0 ]; then
  sudo=""; [ "$(id -u)" -eq 0 ] || sudo=sudo
  echo "installing ${need[*]}"
  $sudo apt-get update -qq && DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${need[@]}" >/dev/null
fi

tmp=$(mktemp -d /tmp/madbp-consumer-XXXXXX)
[ "${KEEP:-0}" = 1 ] && echo "temporary directory: $tmp" || trap 'rm -rf "$tmp"' EXIT
prefix=$tmp/prefix
cp -r tests/consumer "$tmp/src"  # consumers live outside the source tree, as a user's project would
passed=0 failed=0
check() {  # check NAME FUNCTION: runs FUNCTION with its output in $tmp/NAME.log
  local name=$1; shift
  local t0=$SECONDS
  if "$@" >"$tmp/$name.log" 2>&1; then
    passed=$((passed + 1)); echo "ok: $name ($((SECONDS - t0)) s): $(tail -n 1 "$tmp/$name.log")"
  else
    failed=$((failed + 1)); echo "FAILED: $name ($((SECONDS - t0)) s); last lines of its log:"; tail -n 30 "$tmp/$name.log" | sed 's/^/  /'
  fi
}
fail() { echo "$*"; return 1; }

install_prefix() {
  cmake -S "$root" -B "$tmp/build" -DCMAKE_INSTALL_PREFIX="$prefix" \
    -DMADBP_BUILD_TOOL=ON -DMADBP_BUILD_EXAMPLES=OFF -DMADBP_BUILD_TESTS=OFF || return 1
  cmake --build "$tmp/build" --target madbp_madbp || return 1  # the installed tool only, not bench_alloc
  cmake --install "$tmp/build" || return 1
  for f in include/madbp_sim.hpp include/madbp.hpp include/madbp_train.hpp share/madbp/models/madbp-default.safetensors \
           share/cmake/madbp/madbpConfig.cmake share/cmake/madbp/madbpConfigVersion.cmake share/pkgconfig/madbp.pc bin/madbp; do
    [ -f "$prefix/$f" ] || fail "missing $prefix/$f" || return 1
  done
  echo "installed $(find "$prefix" -type f | wc -l) files into a temporary prefix"
}

# The installed tool finds the model installed beside it (madbp::default_model_path), from any
# directory and after the prefix moves: a broken model put beside the moved copy is the one it
# reads. Needing no model, --help and the expert run with MADBP_MODEL naming a missing file.
installed_tool() (  # a subshell: it changes directory
  local moved=$tmp/moved elsewhere=$tmp/elsewhere model=share/madbp/models/madbp-default.safetensors
  mkdir -p "$elsewhere" && cp -r "$prefix" "$moved" || return 1
  cd "$elsewhere" || return 1
  env -u MADBP_MODEL "$prefix/bin/madbp" demo --out demo.svg || return 1
  env -u MADBP_MODEL "$moved/bin/madbp" demo --out moved.svg || return 1
  [ -s demo.svg ] && [ -s moved.svg ] || fail "demo wrote no picture" || return 1
  echo broken >"$moved/$model"
  if env -u MADBP_MODEL "$moved/bin/madbp" demo --out broken.svg 2>err.txt; then fail "the moved tool did not read its own model"; return 1; fi
  grep -q "$moved/bin/../$model" err.txt || fail "error does not name the moved model: $(cat err.txt)" || return 1
  MADBP_MODEL=$prefix/$model "$moved/bin/madbp" demo --out env.svg || return 1
  MADBP_MODEL=/nonexistent "$moved/bin/madbp" eval --help >/dev/null || return 1
  MADBP_MODEL=/nonexistent "$moved/bin/madbp" eval --method expert --agents 2 --episodes 1 || return 1
  echo "installed bin/madbp: demo from $elsewhere with its installed model, also moved; MADBP_MODEL overrides it"
)

run_consumer() {  # run_consumer BINARY MODEL_DIR: plans with the default model the package points it to
  env -u MADBP_MODEL "$1" || return 1
  env -u MADBP_MODEL "$1" | grep -q "planned 4 robots, 15 waypoints each.*model $2/madbp-default.safetensors\$" ||
    fail "expected a plan with the model in $2"
}

cmake_consumer() {
  cmake -S "$tmp/src/cmake" -B "$tmp/b-cmake" -DCMAKE_PREFIX_PATH="$prefix" -DCMAKE_BUILD_TYPE=Release || return 1
  cmake --build "$tmp/b-cmake" || return 1
  run_consumer "$tmp/b-cmake/consumer" "$prefix/share/madbp/models"
}

pkgconfig_consumer() {
  PKG_CONFIG_PATH=$prefix/share/pkgconfig make -C "$tmp/src/pkgconfig" || return 1
  run_consumer "$tmp/src/pkgconfig/consumer" "$prefix/share/pkgconfig/../../share/madbp/models"
}

fetch_consumer() {
  cmake -S "$tmp/src/fetchcontent" -B "$tmp/b-fetch" -DFETCHCONTENT_SOURCE_DIR_MADBP="$root" -DCMAKE_BUILD_TYPE=Release || return 1
  cmake --build "$tmp/b-fetch" || return 1
  [ ! -e "$tmp/b-fetch/_deps/madbp-build/madbp" ] || fail "the subproject built the tool (options should default OFF)" || return 1
  run_consumer "$tmp/b-fetch/consumer" "$root/models"
}

python_check() {
  # The C++ reference, built against the installed package with madbp.pc's flags.
  eval "g++ -O2 $(PKG_CONFIG_PATH=$prefix/share/pkgconfig pkg-config --cflags madbp) -o '$tmp/madbp_ref' \
        examples/python/madbp_ref.cpp $(PKG_CONFIG_PATH=$prefix/share/pkgconfig pkg-config --libs madbp)" || return 1
  "$madbp" collect --maps empty,barrier --n-train-max 2 --episodes 1 --keep-failures --threads 1 --out "$tmp/demos.bin" || return 1
  "$python" examples/python/madbp_io.py "$tmp/demos.bin" || return 1
  "$python" examples/python/check.py "$tmp/madbp_ref" models/madbp-default.safetensors aap.mlp1 "$tmp/demos.bin"
}

# A tiny suite: Table I, dynamic teams and the pictures, 2 episodes, a model directory with only
# the default model (the MAPPO and MADiff cells are recorded as missing). Every run writes to
# results/ under its own directory, so paths in the reports are the same.
shard_check() {
  mkdir -p "$tmp/models" && cp models/madbp-default.safetensors "$tmp/models/" || return 1
  local flags=(--only table1,dynamic,pictures --episodes 2 --models "$tmp/models")
  for run in full again; do
    mkdir -p "$tmp/$run" && (cd "$tmp/$run" && "$madbp" eval --suite paper --threads 2 "${flags[@]}") || return 1
  done
  mkdir -p "$tmp/cluster"
  for i in 0 1; do  # two Slurm array tasks, run here one after the other
    (cd "$tmp/cluster" && SLURM_ARRAY_TASK_ID=$i SLURM_ARRAY_TASK_MIN=0 SLURM_ARRAY_TASK_COUNT=2 SLURM_CPUS_PER_TASK=2 \
      MADBP="$madbp" MADBP_SUITE_FLAGS="${flags[*]}" bash "$root/scripts/slurm-results.sh") || return 1
  done
  # One shard alone leaves cells to do: the merge refuses and runs nothing.
  if (cd "$tmp/cluster" && MADBP="$madbp" "$root/scripts/merge-results.sh" partial results-shards/0 -- "${flags[@]}"); then
    fail "merging one of two shards should have failed"; return 1
  fi
  [ ! -e "$tmp/cluster/partial/index.md" ] || fail "a refused merge wrote reports" || return 1
  (cd "$tmp/cluster" && MADBP="$madbp" "$root/scripts/merge-results.sh" results results-shards/0 results-shards/1 -- "${flags[@]}") \
    | tee "$tmp/merge.out" || return 1
  grep -q "^suite: 0 cells run" "$tmp/merge.out" || fail "the merge ran cells" || return 1
  # The store: the same records as the unsharded run, timings aside.
  local strip='{ s = ""; for (i = 1; i <= NF; i++) if ($i !~ /^(plan_ms|cell_seconds|seconds)=/) s = s "\t" $i; print s }'
  diff <(awk -F'\t' "$strip" "$tmp/full/results/cells.tsv" | sort) <(awk -F'\t' "$strip" "$tmp/cluster/results/cells.tsv" | sort) ||
    fail "merged store differs from the unsharded run's" || return 1
  # Every output that two unsharded runs reproduce byte for byte must come out of the merge the same.
  local same=0 timing=0
  for f in "$tmp/full/results"/*.*; do
    b=$(basename "$f")
    [ "$b" = cells.tsv ] && continue
    [ -f "$tmp/cluster/results/$b" ] || fail "merge lacks $b" || return 1
    if cmp -s "$f" "$tmp/again/results/$b"; then
      cmp "$f" "$tmp/cluster/results/$b" || fail "merged $b differs from the unsharded run's" || return 1
      same=$((same + 1))
    else
      timing=$((timing + 1))  # holds timings (plan_ms): differs between any two runs
    fi
  done
  [ "$same" -ge 20 ] || fail "only $same outputs comparable" || return 1
  echo "2 shards merged: $(grep -c . "$tmp/cluster/results/cells.tsv") store lines, 0 cells run; $same outputs identical to an unsharded run ($timing hold timings)"
}

check install install_prefix
check tool installed_tool
check cmake cmake_consumer
check pkgconfig pkgconfig_consumer
check fetch fetch_consumer
check python python_check
if [ -x "$madbp" ]; then check shards shard_check; else failed=$((failed + 1)); echo "FAILED: shards: $madbp is not built"; fi
echo "$passed passed, $failed failed"
[ "$failed" -eq 0 ]
