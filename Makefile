# kinfly front door. On a fresh Debian 12 machine: `make demo`, then `make test`.
#
#   make build      Release build with Ninja; binaries in build/bin/
#   make test       deps + build + C++ unit tests (ctest) + Python integration tests (pytest)
#   make test-asan  unit tests built with AddressSanitizer + UBSan in build-asan/
#   make fuzz       the depth decoder under libFuzzer + ASan/UBSan (clang, build-fuzz/) for
#                   FUZZ_SECONDS (default 60); `make fuzz-corpus` regenerates its seed corpus
#   make demo       fuse the bundled TUM sample into out/demo (mesh, trajectory, stats)
#   make eval       accuracy on the shared data: TUM ATE (ground + onboard), Replica mesh
#   make bench      depth codec and keyframe delivery over LCM on the TUM sequence; kinfly-fuse
#                   vs Open3D dense SLAM (own .venv-bench); prints, never fails on timings
#   make clean      remove build outputs (build/, build-asan/, build-fuzz/, out/); `make distclean`
#                   also venvs
#
# The shared data folder is <repo>/../shared/data unless KINFLY_DATA says otherwise.

SHELL := /bin/bash
.SHELLFLAGS := -euo pipefail -c
.DEFAULT_GOAL := build

REPO_ROOT := $(abspath $(dir $(lastword $(MAKEFILE_LIST))))
KINFLY_DATA ?= $(abspath $(REPO_ROOT)/../shared/data)
export KINFLY_DATA
# evo imports matplotlib; no display on CI or a drone's companion computer.
export MPLBACKEND := Agg

BUILD_DIR := $(REPO_ROOT)/build
ASAN_DIR := $(REPO_ROOT)/build-asan
FUZZ_DIR := $(REPO_ROOT)/build-fuzz
FUZZ_SECONDS ?= 60
FUZZ_SEEDS := $(REPO_ROOT)/tests/fuzz/corpus/depth_decode
FUSE := $(BUILD_DIR)/bin/kinfly-fuse
CODEC_BENCH := $(BUILD_DIR)/bin/kinfly-codec-bench
TUM_SEQUENCE := $(KINFLY_DATA)/tum_rgbd_freiburg3_teddy_first200/rgbd_dataset_freiburg3_teddy
PY := $(REPO_ROOT)/.venv/bin/python
BENCH_PY := $(REPO_ROOT)/.venv-bench/bin/python
SAMPLE := $(REPO_ROOT)/tests/data/tum_teddy_sample
DEMO_OUT := $(REPO_ROOT)/out/demo
JOBS ?= $(shell nproc)

# Steps run in the order written; ninja and ctest do the parallel work.
.NOTPARALLEL:

.PHONY: deps build test unit-test integration-test test-asan fuzz fuzz-corpus demo eval bench clean \
        distclean

deps:
	@$(REPO_ROOT)/scripts/install-deps.sh

build:
	cmake -S $(REPO_ROOT) -B $(BUILD_DIR) -G Ninja -DCMAKE_BUILD_TYPE=Release
	cmake --build $(BUILD_DIR) -j $(JOBS)

test: deps build unit-test integration-test

unit-test:
	ctest --test-dir $(BUILD_DIR) --output-on-failure -j $(JOBS)

integration-test:
	$(PY) -m pytest $(REPO_ROOT)/tests/integration -v

# Sanitizers slow everything down, so only the unit tests (synthetic, small) run here; the
# micro-benchmarks are left out of this build.
test-asan: deps
	cmake -S $(REPO_ROOT) -B $(ASAN_DIR) -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
	  -DKINFLY_SANITIZE=ON -DKINFLY_BUILD_BENCH=OFF
	cmake --build $(ASAN_DIR) -j $(JOBS)
	ASAN_OPTIONS=detect_leaks=1:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1 \
	  ctest --test-dir $(ASAN_DIR) --output-on-failure -j $(JOBS)

# The committed seeds stay read-only: what libFuzzer finds goes to build-fuzz/corpus, and a crash
# to build-fuzz/crash-*. Only the codec library is compiled for this build.
fuzz: deps
	CC=clang CXX=clang++ cmake -S $(REPO_ROOT) -B $(FUZZ_DIR) -G Ninja \
	  -DCMAKE_BUILD_TYPE=RelWithDebInfo -DKINFLY_FUZZ=ON -DKINFLY_SANITIZE=ON -DKINFLY_BUILD_BENCH=OFF
	cmake --build $(FUZZ_DIR) --target fuzz_depth_decode
	mkdir -p $(FUZZ_DIR)/corpus
	$(FUZZ_DIR)/tests/fuzz_depth_decode -max_total_time=$(FUZZ_SECONDS) -print_final_stats=1 \
	  -artifact_prefix=$(FUZZ_DIR)/ $(FUZZ_DIR)/corpus $(FUZZ_SEEDS)

fuzz-corpus: build
	rm -rf $(FUZZ_SEEDS)
	mkdir -p $(FUZZ_SEEDS)
	$(BUILD_DIR)/tests/make_depth_decode_corpus $(FUZZ_SEEDS)

demo: deps build
	rm -rf $(DEMO_OUT)
	mkdir -p $(DEMO_OUT)
	$(FUSE) --tum $(SAMPLE) --out $(DEMO_OUT)
	@echo
	@echo "kinfly-fuse fused $(SAMPLE) into:"
	@echo "  mesh        $(DEMO_OUT)/mesh.ply"
	@echo "  trajectory  $(DEMO_OUT)/trajectory.tum"
	@echo "  render      $(DEMO_OUT)/render.png"
	@echo "  statistics  $(DEMO_OUT)/stats.json"
	@echo "ATE against the sample's ground truth (first frames have no GT within 20 ms):"
	@$(PY) $(REPO_ROOT)/tests/tools/kinfly_eval.py ate $(DEMO_OUT)/trajectory.tum $(SAMPLE)/groundtruth.txt

eval: deps build
	@test -d $(KINFLY_DATA) || { echo "no shared data at $(KINFLY_DATA) (set KINFLY_DATA)"; exit 1; }
	$(PY) $(REPO_ROOT)/tests/tools/kinfly_eval.py all --fuse $(FUSE) --data $(KINFLY_DATA) \
	  --out $(REPO_ROOT)/out/eval

# Open3D lives only in .venv-bench, never in the product environment (.venv). The codec bench
# runs on one thread and fails only if a frame does not come back bit for bit. The link bench
# needs root (or sudo) for its network namespace.
bench: deps build
	mkdir -p $(REPO_ROOT)/out/bench
	$(CODEC_BENCH) --tum $(TUM_SEQUENCE) | tee $(REPO_ROOT)/out/bench/codec.json
	$(PY) $(REPO_ROOT)/tests/bench/bench_link.py --data $(KINFLY_DATA) --out $(REPO_ROOT)/out/bench
	@$(REPO_ROOT)/scripts/install-deps.sh --bench
	OMP_NUM_THREADS=2 $(BENCH_PY) $(REPO_ROOT)/tests/bench/bench_vs_open3d.py --fuse $(FUSE) \
	  --data $(KINFLY_DATA) --out $(REPO_ROOT)/out/bench

clean:
	rm -rf $(BUILD_DIR) $(ASAN_DIR) $(FUZZ_DIR) $(REPO_ROOT)/out

distclean: clean
	rm -rf $(REPO_ROOT)/.venv $(REPO_ROOT)/.venv-bench
