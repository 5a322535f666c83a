# madbp - build, test, benchmark. `make demo` and `make test` are the whole set-up.
SHELL    := /bin/bash
CXX      ?= g++
SUDO     := $(shell [ "$$(id -u)" -eq 0 ] || echo sudo)
EIGEN    := /usr/include/eigen3
INCLUDES := -I. -Itool -Itests -isystem $(EIGEN)
WARN     := -Wall -Wextra -Wno-unused-parameter
# The tool and benchmarks build with -O3 (SPEC 9); tests with -O2 and line tables only (-g1:
# backtraces keep file:line; the compile takes a third less time than with -g). ARCH is the
# target-CPU flag (empty for a portable or cross build). -MMD -MP: each object tracks the
# headers it includes.
ARCH     ?= -march=native
DEPFLAGS := -MMD -MP
CXXFLAGS_FAST := -std=c++17 -O3 $(ARCH) -fopenmp -DNDEBUG $(WARN) $(INCLUDES) $(DEPFLAGS)
CXXFLAGS_TEST := -std=c++17 -O2 $(ARCH) -fopenmp -g1 $(WARN) $(INCLUDES) $(DEPFLAGS)
CXXFLAGS_SAN  := -std=c++17 -O1 -g1 -fopenmp -fsanitize=address,undefined -fno-omit-frame-pointer $(WARN) $(INCLUDES) $(DEPFLAGS)

BUILD        ?= build
# OpenMP threads sleep instead of spinning while they wait: on a busy 2-core machine spinning
# made 2-thread training up to 20x slower (docs/speed.md). Override in the environment.
export OMP_WAIT_POLICY ?= passive
TEST_SRCS    ?= $(wildcard tests/test_*.cpp)
TEST_OBJS    := $(patsubst tests/%.cpp,$(BUILD)/tests/%.o,$(TEST_SRCS))
SAN_OBJS     := $(patsubst tests/%.cpp,$(BUILD)/san/%.o,$(TEST_SRCS))
EXAMPLE_SRCS := $(wildcard examples/*.cpp)
EXAMPLES     := $(patsubst examples/%.cpp,$(BUILD)/%,$(EXAMPLE_SRCS))
# The madbp tool (tool/: CLI, method registry, evaluation suite, benchmarks) and the allocation
# benchmark, which replaces malloc and so is a program of its own.
TOOLS        := $(BUILD)/madbp $(BUILD)/bench_alloc

.PHONY: all deps check-headers test test-sanitize demo bench fuzz fuzz-build model dagger mappo-models madiff-models paper-models results maps-eval clean
all: deps $(TOOLS) $(EXAMPLES)

# Install Eigen and doctest through apt when their headers are missing.
deps:
	@if [ ! -f $(EIGEN)/Eigen/Dense ] || [ ! -f /usr/include/doctest/doctest.h ]; then \
	  echo "installing libeigen3-dev doctest-dev"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq libeigen3-dev doctest-dev; \
	fi

$(BUILD)/%: tool/%.cpp | deps
	@mkdir -p $(BUILD)
	$(CXX) $(CXXFLAGS_FAST) -o $@ $<

$(BUILD)/%: examples/%.cpp | deps
	@mkdir -p $(BUILD)
	$(CXX) $(CXXFLAGS_FAST) -o $@ $<

$(BUILD)/tests/%.o: tests/%.cpp | deps
	@mkdir -p $(BUILD)/tests
	$(CXX) $(CXXFLAGS_TEST) -c -o $@ $<

$(BUILD)/run_tests: $(BUILD)/tests/main.o $(TEST_OBJS)
	$(CXX) $(CXXFLAGS_TEST) -o $@ $^

$(BUILD)/san/%.o: tests/%.cpp | deps
	@mkdir -p $(BUILD)/san
	$(CXX) $(CXXFLAGS_SAN) -c -o $@ $<

$(BUILD)/run_tests_san: $(BUILD)/san/main.o $(SAN_OBJS)
	$(CXX) $(CXXFLAGS_SAN) -o $@ $^

# Each header compiles on its own (no include-order dependencies), warning-free.
check-headers: deps
	@set -e; for h in madbp_sim.hpp madbp.hpp madbp_train.hpp; do \
	  echo "#include \"$$h\"" | $(CXX) -std=c++17 -fsyntax-only -fopenmp $(WARN) -Werror $(INCLUDES) -x c++ - ; \
	  echo "$$h compiles on its own"; done

# Runs every test; the last line is "N passed, N failed" (doctest's test-case counts).
# The test objects build in parallel on every core even when `make test` is called without -j.
JOBS ?= $(shell nproc 2>/dev/null || echo 2)
test: deps
	@$(MAKE) --no-print-directory -j$(JOBS) $(BUILD)/run_tests
	@set -o pipefail; $(BUILD)/run_tests $(TEST_ARGS) 2>&1 | tee $(BUILD)/test.log; status=$$?; \
	 tests/summary.sh $(BUILD)/test.log; exit $$status

# The same suite under AddressSanitizer + UndefinedBehaviorSanitizer (slow tests skipped).
test-sanitize: deps $(BUILD)/run_tests_san
	@set -o pipefail; ASAN_OPTIONS=detect_leaks=1 UBSAN_OPTIONS=halt_on_error=1:print_stacktrace=1 \
	 $(BUILD)/run_tests_san --test-case-exclude='*[slow]*' 2>&1 | tee $(BUILD)/test-san.log; status=$$?; \
	 tests/summary.sh $(BUILD)/test-san.log; exit $$status

demo: all
	$(BUILD)/madbp demo

bench: all
	$(BUILD)/madbp bench
	$(BUILD)/madbp bench --nn
	$(BUILD)/madbp bench --plan
	$(BUILD)/madbp bench --plan --agents 64,256,1024 --plans 3 --no-expert
	$(BUILD)/madbp bench --plan --map obstacles --agents 64,256,1024 --plans 3 --no-expert --episode-steps 100
	$(BUILD)/bench_alloc

# The shipped default model, reproducibly: expert demonstrations (3 maps, 1-4 robots, 500
# episodes each, 30% of them interaction scenes: swaps, crossings, gaps, corridors, parked robots,
# circles), then 20,000 steps of training on 2 data-parallel replicas in the Local scene frame
# with route subgoals 1.5 units ahead (~12 min on 2 cores; docs/experiments.md "Deploy large").
# The datasets are collected once into build/ (delete them to collect again); the paper models
# below are trained on the same mix.
MODEL_FLAGS ?= --steps 20000 --batch 64 --threads 2 --seed 0 --frame local --subgoal 1.5
DEMOS_FLAGS := --episodes 500 --threads 2 --seed 0 --scenarios all:0.3
$(BUILD)/demos-mix.bin: | $(BUILD)/madbp
	$(BUILD)/madbp collect $(DEMOS_FLAGS) --out $@
$(BUILD)/demos-mix-empty.bin: | $(BUILD)/madbp
	$(BUILD)/madbp collect --maps empty $(DEMOS_FLAGS) --out $@
model: all $(BUILD)/demos-mix.bin
	$(BUILD)/madbp train --data $(BUILD)/demos-mix.bin --out models/madbp-default.safetensors $(MODEL_FLAGS)
	rm -f models/madbp-default.safetensors.train

# DAgger (issue 12; docs/experiments.md "DAgger"): from the shipped model, 4 rounds of 480
# rollouts (half of them interaction scenes), a label at every 2nd visited state, 3000 fine-tune
# steps per round (~12 min on 2 cores; resumable: rerun to continue). The measured run, with the
# filter weights of the time (--set follower.priority_weight=1). It did not beat the shipped model, so its
# output stays in build/.
dagger: all $(BUILD)/demos-mix.bin
	@mkdir -p $(BUILD)/dagger
	$(BUILD)/madbp dagger --data $(BUILD)/demos-mix.bin --out $(BUILD)/dagger/a.safetensors --rounds 4 --episodes 40 \
	  --scenarios all:0.5 --steps 3000 --threads 2 --set follower.priority_weight=1 --resume

# libFuzzer targets tests/fuzz_NAME.cpp (ASan + UBSan): checkpoint reader, scene parser,
# dataset reader, the tool's flag parser (args), MovingAI import (movingai). `make fuzz` builds them all (`make fuzz-build` only builds) and runs each for
# FUZZ_SECONDS (600 for the release check) on build/fuzz-corpus/NAME, seeded from
# tests/fuzz-seeds (checkpoint) or tests/fuzz-seeds-NAME; FUZZ_TARGETS=scene runs some.
FUZZ_SECONDS ?= 60
FUZZ_TARGETS ?= checkpoint scene dataset args movingai
FUZZ_CXXFLAGS := -std=c++17 -O1 -g -fopenmp -fsanitize=fuzzer,address,undefined $(INCLUDES)
fuzz-build: deps
	@mkdir -p $(BUILD)
	@set -e; for t in $(FUZZ_TARGETS); do \
	  echo "clang++ $(FUZZ_CXXFLAGS) -o $(BUILD)/fuzz_$$t tests/fuzz_$$t.cpp"; \
	  clang++ $(FUZZ_CXXFLAGS) -o $(BUILD)/fuzz_$$t tests/fuzz_$$t.cpp; done
fuzz: fuzz-build
	@set -e; for t in $(FUZZ_TARGETS); do seeds=tests/fuzz-seeds-$$t; [ $$t = checkpoint ] && seeds=tests/fuzz-seeds; \
	  mkdir -p $(BUILD)/fuzz-corpus/$$t; \
	  $(BUILD)/fuzz_$$t -max_total_time=$(FUZZ_SECONDS) -max_len=4096 $(BUILD)/fuzz-corpus/$$t $$seeds; done

# MAPPO policies (SPEC 3.3; docs/design.md "MAPPO"): map:n:iterations (~40 min on 2 cores).
# On the obstacle map: 2x256 networks and a reward for being at the goal (docs/experiments.md,
# "MAPPO stalls beside its goal"). On the barrier: the route goal 1.5 ahead observed, as
# MA-DBP's model is told, and shaping on the route distance (docs/experiments.md, "MAPPO sees
# the route").
MAPPO_CELLS := empty:1:100 empty:2:200 empty:3:250 empty:4:300 empty:6:400 empty:8:500 \
               obstacles:2:500 obstacles:3:500 obstacles:4:500 barrier:2:500 barrier:3:500 barrier:4:600
MAPPO_OBSTACLE_FLAGS := --hidden 256 --reward-at-goal 0.2
BARRIER_ROUTE_GOAL := 1.5
MAPPO_BARRIER_FLAGS := --route-goal $(BARRIER_ROUTE_GOAL) --reward-route
mappo-models: $(BUILD)/madbp
	@mkdir -p models/mappo
	@set -e; for cell in $(MAPPO_CELLS); do IFS=: read map n it <<< "$$cell"; \
	  case $$map in obstacles) extra="$(MAPPO_OBSTACLE_FLAGS)";; barrier) extra="$(MAPPO_BARRIER_FLAGS)";; *) extra="";; esac; \
	  $(BUILD)/madbp mappo --map $$map --agents $$n --iterations $$it --threads 2 $$extra \
	    --out models/mappo/$$map-$$n.safetensors; done

# Every table and figure of the paper plus ours (docs/evaluation.md): results/*.md, *.csv,
# *.svg; resumable (rerun to continue), shardable with SUITE_FLAGS='--shard i/N'.
results: $(BUILD)/madbp
	$(BUILD)/madbp eval --suite paper --threads 2 $(SUITE_FLAGS)

# The MovingAI tuning maps of issue 46 (maps/movingai/README.md: every .map there; a map
# without .scen files gets rows drawn per seed, `convert --random-scen`):
# MA-DBP, the guided expert and the straight line at cell 0.3 and 0.25 with 4, 8, 16 and 32
# robots, seeds 0-99 (hours on 2 cores;
# not part of `make test`). One row per episode in results/maps/episodes.tsv, the summary in
# results/maps/episodes.md; narrower with e.g. `make maps-eval MAPS=maze-32-32-4 SEEDS="0 9"`.
maps-eval: $(BUILD)/madbp
	MADBP=$(BUILD)/madbp OUT=results/maps/episodes.tsv JOBS=$(JOBS) scripts/maps_eval.sh

# MADiff baselines (SPEC 3.4; docs/design.md "MADiff"): per map:n:steps, 300 episodes of the
# shipped MAPPO policy of that cell (the paper trains MADiff on MAPPO's data; successful episodes
# only), then one model on one thread (1.5-10 min each on the 2-core machine), sampling in 5
# steps. Steps per cell: the best of 1000, 2000, ..., 20000 on tuning seeds 1000-1099
# (docs/experiments.md "MADiff checkpoints"). On the barrier MADiff observes the route goal, as
# MAPPO there does, and its steps are the best of 2000, 4000, ..., 20000 ("MADiff sees the route").
MADIFF_CELLS := empty:2:17000 empty:4:20000 empty:6:20000 obstacles:2:19000 obstacles:3:19000 obstacles:4:14000 \
                barrier:2:18000 barrier:3:20000 barrier:4:18000
madiff-models: $(BUILD)/madbp
	@mkdir -p models/madiff
	@set -e; for cell in $(MADIFF_CELLS); do IFS=: read map n steps <<< "$$cell"; \
	  case $$map in barrier) extra="--route-goal $(BARRIER_ROUTE_GOAL)";; *) extra="";; esac; \
	  $(BUILD)/madbp collect --demonstrator mappo --model "models/mappo/$$map-{n}.safetensors" --maps $$map \
	    --n-train-min $$n --n-train-max $$n --episodes 300 --seed 0 --threads 1 --out $(BUILD)/demos-madiff-$$map-$$n.bin; \
	  $(BUILD)/madbp madiff --map $$map --agents $$n --steps $$steps --sample-steps 5 --threads 1 --seed 0 $$extra \
	    --data $(BUILD)/demos-madiff-$$map-$$n.bin --out models/madiff/$$map-$$n.safetensors; \
	  rm -f models/madiff/$$map-$$n.safetensors.train; done

# The models of the paper's figures (docs/evaluation.md; `madbp eval --suite paper` reads them),
# with the default model's recipe (data mix, local frame, route subgoals): the Fig. 4 upscaling
# models trained on 1..k robots of all three maps for as long as the default model (k = 4 is the
# default model), and the ablations of Table II and the horizon sweep on the empty map (as the
# paper does) with 2,000 steps each (~50 min on 2 cores in all).
PAPER_ABLATION_STEPS ?= 2000
PAPER_TRAIN          := --batch 64 --threads 2 --seed 0
paper-models: all $(BUILD)/demos-mix.bin $(BUILD)/demos-mix-empty.bin
	@mkdir -p models/paper
	@set -e; for k in 2 3; do \
	  $(BUILD)/madbp train --data $(BUILD)/demos-mix.bin --n-train-max $$k $(MODEL_FLAGS) \
	    --out models/paper/madbp-n$$k.safetensors; done
	@set -e; for cfg in MW:AAP:16:64 MW:LE:16:64 CT:AAP:104:16 CT:LE:104:16; do IFS=: read win proc h batch <<< "$$cfg"; \
	  for k in 2 3 4; do \
	    $(BUILD)/madbp train --data $(BUILD)/demos-mix-empty.bin --n-train-max $$k --steps $(PAPER_ABLATION_STEPS) $(PAPER_TRAIN) \
	      --window $$win --processor $$proc --horizon $$h --batch $$batch --out models/paper/ablation-$$win-$$proc-n$$k.safetensors; \
	  done; done
	@set -e; for h in 8 32; do \
	  $(BUILD)/madbp train --data $(BUILD)/demos-mix-empty.bin --n-train-max 4 --steps $(PAPER_ABLATION_STEPS) $(PAPER_TRAIN) \
	    --horizon $$h --out models/paper/ablation-MW-AAP-n4-h$$h.safetensors; done
	rm -f models/paper/*.train

clean:
	rm -rf $(BUILD)

# --- Packaging (docs/packaging.md) -------------------------------------------------------------
.PHONY: test-consumer aarch64 test-aarch64

# Installs with CMake (the tool too) into a temporary prefix, runs the installed tool from
# elsewhere, and builds/runs the find_package, pkg-config and FetchContent consumers; checks the Python readers against C++ and the Slurm shard merge on a
# tiny suite. The last line is "N passed, N failed".
test-consumer: $(BUILD)/madbp
	tests/consumer/check.sh

# Cross build for 64-bit ARM (Debian's g++-aarch64-linux-gnu, installed when missing): the tool
# and the tests in $(AARCH64_BUILD), ARCH empty (AARCH64_ARCH=-mcpu=cortex-a76 for a given
# board). doctest is header-only: its host headers are reached through a directory of its own.
# `make test-aarch64` runs the suite under qemu-user with the cross libraries in AARCH64_SYSROOT
# and ends with "N passed, N failed"; AARCH64_TEST_ARGS passes doctest options.
AARCH64_CXX       ?= aarch64-linux-gnu-g++
AARCH64_ARCH      ?=
AARCH64_BUILD     ?= $(BUILD)/aarch64
AARCH64_SYSROOT   ?= /usr/aarch64-linux-gnu
QEMU_AARCH64      ?= qemu-aarch64
AARCH64_TEST_ARGS ?=
aarch64: deps
	@command -v $(AARCH64_CXX) >/dev/null || { echo "installing g++-aarch64-linux-gnu"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq g++-aarch64-linux-gnu; }
	@mkdir -p $(AARCH64_BUILD)/include && ln -sfn /usr/include/doctest $(AARCH64_BUILD)/include/doctest
	$(MAKE) BUILD=$(AARCH64_BUILD) CXX=$(AARCH64_CXX) ARCH='$(AARCH64_ARCH)' \
	  INCLUDES='$(INCLUDES) -isystem $(AARCH64_BUILD)/include' $(AARCH64_BUILD)/madbp $(AARCH64_BUILD)/run_tests
	@file $(AARCH64_BUILD)/madbp 2>/dev/null || true

test-aarch64: aarch64
	@command -v $(QEMU_AARCH64) >/dev/null || { echo "installing qemu-user"; \
	  $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq qemu-user; }
	@set -o pipefail; $(QEMU_AARCH64) -L $(AARCH64_SYSROOT) $(AARCH64_BUILD)/run_tests $(AARCH64_TEST_ARGS) 2>&1 \
	  | tee $(AARCH64_BUILD)/test.log; status=$$?; tests/summary.sh $(AARCH64_BUILD)/test.log; exit $$status

-include $(wildcard $(BUILD)/*.d $(BUILD)/tests/*.d $(BUILD)/san/*.d)
