# kinfly front door. On a fresh Debian 12 machine: `make demo`, then `make test`.
#
# Every target that needs packages first runs scripts/install-deps.sh with the groups it uses
# (apt only for what dpkg reports missing, pip only when a requirements file changed; `--help`
# lists the groups): demo (compiler, CMake, the libraries kinfly-fw links, Python; .venv with
# the ground package), unit (+ GoogleTest), test (demo + unit + the integration tests' tools),
# fuzz (unit + clang), aarch64 (cross compiler, qemu-user, mmdebstrap), image (aarch64 +
# qemu-user-static, binfmt-support, GRUB and disk tools), bench (demo + valgrind; .venv-bench).
#
#   make build      Release build with Ninja, everything (programs and unit tests); binaries in
#                   build/bin/. Installs nothing.
#   make test       deps test + build + C++ unit tests (ctest) + Python tests (pytest)
#   make test-asan  deps unit; unit tests built with AddressSanitizer + UBSan in build-asan/
#   make fuzz       deps fuzz; the depth decoder and the ground's chunk assembly under libFuzzer +
#                   ASan/UBSan (clang, build-fuzz/), FUZZ_SECONDS (default 60) split between them;
#                   `make fuzz-corpus` regenerates their seed corpora
#   make demo       deps demo; builds only kinfly-fw and kinfly-keygen; a recorded flight end to
#                   end: kinfly-fw replays the shipped LCM log to kinfly-ground over LCM in a
#                   network namespace; outputs in out/demo
#   make sim        deps demo, sim; kinfly-sim flies the drone in the simulated room through the real
#                   kinfly-fw and kinfly-ground in lockstep in a network namespace (the room
#                   tour: sim/missions/room_tour.toml); outputs in out/sim (docs/sim.md)
#   make bench-sim  deps demo, sim; the closed-loop flight figures over seeds 1-3, each flown as
#                   make sim flies (at 320x240): hover calm and in wind and gusts, the figure
#                   eight at 1 and 2 m/s, a 2 m/s wind step, the room tour; ~25 min; medians
#                   printed, out/bench/sim_flights.json; fails only if a flight does not fly
#                   through
#   make demo-runs  deps demo; make demo's flight DEMO_RUNS times (20) on the machine as it is,
#                   then DEMO_BUSY_RUNS times (10) beside two busy loops; out/bench/demo_runs_*.json
#   make test-runs  make test, then its tests TEST_RUNS times (3) beside two busy loops;
#                   out/bench/make_test_runs.json
#   make soak       deps demo; an hours-long flight (SOAK_MINUTES, 60): the shipped flight log
#                   bounced (forward, backward ...) through kinfly-fw and kinfly-ground in a
#                   network namespace, memory sampled on both ends; fails on memory growth, an
#                   uncounted drop or a stall (tests/system/soak.py); out/soak/soak.json. Not
#                   part of make test, which flies a 2-minute soak (tests/system/test_soak.py)
#   make eval       deps demo; accuracy on the shared data: TUM ATE (ground + onboard), Replica mesh
#   make bench      deps bench, the aarch64 build; depth codec and keyframe delivery over LCM on the
#                   TUM sequence; the drone's figures (kinfly-fw: odometry time, memory, ATE,
#                   keyframes, instructions per frame of the native build by callgrind and of the
#                   aarch64 build under qemu-aarch64, with NEON's share); kinfly-fw and
#                   kinfly-ground flying 3 minutes each uncapped and through 2 and 0.3 Mbit/s
#                   caps: the drone's send budget, keyframe sizes and
#                   age at the ground, odometry rate (out/bench/fw_link.json); incremental
#                   meshing against a full re-mesh (out/bench/mesh.json); the flight stack's
#                   body-rate and attitude step responses, geometric and LQR, on the test plant
#                   (out/bench/flight.json) with hover, figure-eight and wind flights, and its
#                   cost per 1 kHz tick, CPU time and callgrind instructions with the Cortex-A72
#                   share (out/bench/flight_cost.json); the figure eight beside RotorPy's SE3
#                   controller flying the same reference (out/bench/flight_oracle.json);
#                   kinfly-fuse vs Open3D dense SLAM (own .venv-bench); the simulator's own speed
#                   at 320x240 and 640x480 (out/bench/sim.json); prints, never fails on timings
#   make firmware-aarch64  deps aarch64; kinfly-fw, the link tools and the unit tests for aarch64
#                   (cross compiler + Debian arm64 sysroot, build-aarch64/)
#   make test-aarch64  deps demo, unit, image; the above + both boards' images; unit tests (while
#                   the images are made) and a replay under qemu-aarch64, alone and against the
#                   native kinfly-ground (hardware in the loop, a network namespace: root or
#                   sudo), the image tests (the uefi image booted, the rpi4 image checked)
#   make aarch64-unit-tests  the above's unit tests under qemu-aarch64 alone
#   make qemu-plugin  the QEMU plugin counting the aarch64 build's instructions (make bench),
#                   built against the installed qemu-user's own source (fetched from Debian once)
#   make package-aarch64  the kinfly-fw .deb (arm64) in build-aarch64/pkg/
#   make image [BOARD=uefi|rpi4]  deps image; flashable arm64 disk image for a UEFI board or a
#                   Raspberry Pi 4, build-aarch64/kinfly-BOARD-arm64.img (root)
#   make flash IMAGE=... DEVICE=/dev/sdX CONFIRM=yes  write the image to an SD card (checked)
#   make deploy HOST=user@drone  install the .deb on a running drone over ssh
#   make deps       every package group; `make deps-GROUP` one of them
#   make clean      remove build outputs (build/, build-asan/, build-fuzz/, build-aarch64/, out/);
#                   `make distclean` also venvs
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
# One seed corpus per fuzz target, tests/fuzz/corpus/<name> for fuzz_<name>.
FUZZ_TARGETS := depth_decode chunk_assemble
FUZZ_SEEDS := $(REPO_ROOT)/tests/fuzz/corpus
# Each target's equal share of FUZZ_SECONDS, at least 1 (libFuzzer reads 0 as "no limit").
FUZZ_SECONDS_EACH = $(shell echo $$(( $(FUZZ_SECONDS) / $(words $(FUZZ_TARGETS)) > 0 ? \
                                      $(FUZZ_SECONDS) / $(words $(FUZZ_TARGETS)) : 1 )))
FUSE := $(BUILD_DIR)/bin/kinfly-fuse
CODEC_BENCH := $(BUILD_DIR)/bin/kinfly-codec-bench
MESH_BENCH := $(BUILD_DIR)/bin/kinfly-mesh-bench
TUM_SEQUENCE := $(KINFLY_DATA)/tum_rgbd_freiburg3_teddy_first200/rgbd_dataset_freiburg3_teddy
PY := $(REPO_ROOT)/.venv/bin/python
BENCH_PY := $(REPO_ROOT)/.venv-bench/bin/python
DEMO_OUT := $(REPO_ROOT)/out/demo
JOBS ?= $(shell nproc)
AARCH64_DIR := $(REPO_ROOT)/build-aarch64
AARCH64_SYSROOT := $(AARCH64_DIR)/sysroot
AARCH64_BUILD := $(AARCH64_DIR)/build
AARCH64_PKG := $(AARCH64_DIR)/pkg
# Whatever version CMakeLists.txt gives (a shell glob: package-aarch64 leaves exactly one).
AARCH64_DEB := $(AARCH64_PKG)/kinfly-fw_*_arm64.deb
BOARD ?= uefi
IMAGE ?= $(AARCH64_DIR)/kinfly-$(BOARD)-arm64.img

# Steps run in the order written; ninja and ctest do the parallel work.
.NOTPARALLEL:

# Each target installs only the package groups it uses (scripts/install-deps.sh --help).
DEPS_GROUPS := demo sim unit test fuzz aarch64 image bench
DEPS_TARGETS := $(addprefix deps-,$(DEPS_GROUPS))

.PHONY: deps $(DEPS_TARGETS) build test unit-test python-test test-asan fuzz fuzz-corpus demo sim \
        sim-programs bench-sim sim-two \
        demo-runs test-runs soak eval bench clean distclean firmware-aarch64 test-aarch64 \
        aarch64-unit-tests qemu-plugin package-aarch64 image \
        flash deploy

deps:
	@$(REPO_ROOT)/scripts/install-deps.sh all

$(DEPS_TARGETS): deps-%:
	@$(REPO_ROOT)/scripts/install-deps.sh $*

# The Release tree, whole: programs, unit tests and their tools.
build:
	cmake -S $(REPO_ROOT) -B $(BUILD_DIR) -G Ninja -DCMAKE_BUILD_TYPE=Release -DKINFLY_BUILD_TESTS=ON
	cmake --build $(BUILD_DIR) -j $(JOBS)

# $(call build_programs,TARGET...): only these targets of the Release tree. A new tree is
# configured without the unit tests (no GoogleTest needed); an existing one keeps what it has, so
# `make demo` and `make test` share build/ in either order without a clean or a flip-flopping
# reconfigure.
define build_programs
cmake -S $(REPO_ROOT) -B $(BUILD_DIR) -G Ninja -DCMAKE_BUILD_TYPE=Release \
  $(if $(wildcard $(BUILD_DIR)/CMakeCache.txt),,-DKINFLY_BUILD_TESTS=OFF)
cmake --build $(BUILD_DIR) -j $(JOBS) --target $(1)
endef

# What scripts/demo.py runs from build/bin (the ground station comes from .venv).
DEMO_PROGRAMS := kinfly-fw kinfly-keygen
# What the benchmarks run from build/bin (tests/bench/*.py; bench_ground flies the demo's way).
BENCH_PROGRAMS := kinfly-codec-bench kinfly-mesh-bench kinfly-link-bench kinfly-fuse kinfly-tum-to-log \
                  kinfly-flight-bench $(DEMO_PROGRAMS)

test: deps-test build unit-test python-test

unit-test:
	ctest --test-dir $(BUILD_DIR) --output-on-failure -j $(JOBS)

# The aarch64 tests (marker aarch64) need the cross build and the image: make test-aarch64.
# The slowest 25 are listed at the end: CI's time is kept under an hour (the brief).
python-test:
	$(PY) -m pytest $(REPO_ROOT)/tests -v -m "not aarch64" --durations=25

# Sanitizers slow everything down, so only the unit tests (synthetic, small) are built and run here.
test-asan: deps-unit
	cmake -S $(REPO_ROOT) -B $(ASAN_DIR) -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
	  -DKINFLY_SANITIZE=ON
	cmake --build $(ASAN_DIR) -j $(JOBS) --target kinfly-unit-tests
	ASAN_OPTIONS=detect_leaks=1:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1 \
	  ctest --test-dir $(ASAN_DIR) --output-on-failure -j $(JOBS)

# The committed seeds stay read-only: what libFuzzer finds goes to build-fuzz/corpus/<name>, and a
# crash to build-fuzz/<name>-crash-*. Only the fuzz targets and the libraries under them (the codec,
# the link and the engine under it) are compiled for this build. Each target gets an equal share of
# FUZZ_SECONDS, so the whole run takes as long as one target used to.
fuzz: deps-fuzz
	CC=clang CXX=clang++ cmake -S $(REPO_ROOT) -B $(FUZZ_DIR) -G Ninja \
	  -DCMAKE_BUILD_TYPE=RelWithDebInfo -DKINFLY_FUZZ=ON -DKINFLY_SANITIZE=ON
	cmake --build $(FUZZ_DIR) -j $(JOBS) --target $(addprefix fuzz_,$(FUZZ_TARGETS))
	for name in $(FUZZ_TARGETS); do \
	  mkdir -p $(FUZZ_DIR)/corpus/$$name; \
	  $(FUZZ_DIR)/tests/fuzz_$$name -max_total_time=$(FUZZ_SECONDS_EACH) \
	    -print_final_stats=1 -artifact_prefix=$(FUZZ_DIR)/$$name- \
	    $(FUZZ_DIR)/corpus/$$name $(FUZZ_SEEDS)/$$name; \
	done

fuzz-corpus: build
	for name in $(FUZZ_TARGETS); do \
	  rm -rf $(FUZZ_SEEDS)/$$name; \
	  mkdir -p $(FUZZ_SEEDS)/$$name; \
	  $(BUILD_DIR)/tests/make_$${name}_corpus $(FUZZ_SEEDS)/$$name; \
	done

# The drone (kinfly-fw replaying the shipped flight log) and the ground station (kinfly-ground)
# over LCM multicast in a private network namespace; outputs in out/demo.
demo: deps-demo
	$(call build_programs,$(DEMO_PROGRAMS))
	$(PY) $(REPO_ROOT)/scripts/demo.py --out $(DEMO_OUT)

# The simulator, kinfly-fw and kinfly-ground in a network namespace (scripts/sim.py); the tree is
# configured with the simulator whatever it had (KINFLY_BUILD_SIM), and without the unit tests if
# new, as for the demo.
SIM_OUT := $(REPO_ROOT)/out/sim
sim: sim-programs
	$(PY) $(REPO_ROOT)/scripts/sim.py --out $(SIM_OUT)

sim-programs: deps-demo deps-sim
	cmake -S $(REPO_ROOT) -B $(BUILD_DIR) -G Ninja -DCMAKE_BUILD_TYPE=Release -DKINFLY_BUILD_SIM=ON \
	  $(if $(wildcard $(BUILD_DIR)/CMakeCache.txt),,-DKINFLY_BUILD_TESTS=OFF)
	cmake --build $(BUILD_DIR) -j $(JOBS) --target kinfly-fw kinfly-keygen kinfly-sim

bench-sim: sim-programs
	$(PY) $(REPO_ROOT)/tests/bench/bench_sim_flights.py --out $(REPO_ROOT)/out/bench

# Two drones in the simulated room, their maps merged by one ground station (scripts/two_drones.py).
# SIM_TWO_SCENE=office0: Replica's office scaled by 1.5, from the shared data.
SIM_TWO_SCENE ?= room
sim-two: sim-programs
	$(PY) $(REPO_ROOT)/scripts/two_drones.py --scene $(SIM_TWO_SCENE) --out $(REPO_ROOT)/out/sim_two

# How often the demo's flight holds: every keyframe fused, every output written, an ATE; on a
# machine as it is, then with both cores of a 2-core machine busy with other work.
DEMO_RUNS ?= 20
DEMO_BUSY_RUNS ?= 10
demo-runs: deps-demo
	$(call build_programs,$(DEMO_PROGRAMS))
	$(PY) $(REPO_ROOT)/tests/bench/demo_runs.py --runs $(DEMO_RUNS) --out $(REPO_ROOT)/out/bench
	$(PY) $(REPO_ROOT)/tests/bench/demo_runs.py --runs $(DEMO_BUSY_RUNS) --busy 2 \
	  --out $(REPO_ROOT)/out/bench

# make test's own steps TEST_RUNS times (3) with both cores of a 2-core machine busy with other
# work; out/bench/make_test_runs.json.
TEST_RUNS ?= 3
test-runs: test
	$(PY) $(REPO_ROOT)/tests/bench/make_test_runs.py --runs $(TEST_RUNS) --out $(REPO_ROOT)/out/bench

# An hour of flight (SOAK_MINUTES) with memory sampled on both ends; SOAK_ARGS passes more
# (--busy 2, --sequence: tests/system/soak.py --help).
SOAK_MINUTES ?= 60
SOAK_ARGS ?=
soak: deps-demo
	$(call build_programs,$(DEMO_PROGRAMS) kinfly-tum-to-log)
	$(PY) $(REPO_ROOT)/tests/system/soak.py --minutes $(SOAK_MINUTES) --out $(REPO_ROOT)/out/soak \
	  $(SOAK_ARGS)

eval: deps-demo
	@test -d $(KINFLY_DATA) || { echo "no shared data at $(KINFLY_DATA) (set KINFLY_DATA)"; exit 1; }
	$(call build_programs,kinfly-fuse)
	$(PY) $(REPO_ROOT)/tests/eval/kinfly_eval.py all --fuse $(FUSE) --data $(KINFLY_DATA) \
	  --out $(REPO_ROOT)/out/eval

# Open3D and RotorPy live only in .venv-bench, never in the product environment (.venv). The
# codec bench runs on one thread and fails only if a frame does not come back bit for bit. The
# link benches need root (or sudo) for their network namespaces, nft for the lossy links and tc
# for the caps; bench_fw_link fails only if kinfly-fw or kinfly-ground does.
bench: deps-bench firmware-aarch64 qemu-plugin
	cmake -S $(REPO_ROOT) -B $(BUILD_DIR) -G Ninja -DCMAKE_BUILD_TYPE=Release -DKINFLY_BUILD_SIM=ON \
	  $(if $(wildcard $(BUILD_DIR)/CMakeCache.txt),,-DKINFLY_BUILD_TESTS=OFF)
	cmake --build $(BUILD_DIR) -j $(JOBS) --target $(BENCH_PROGRAMS) kinfly-sim-bench
	mkdir -p $(REPO_ROOT)/out/bench
	$(BUILD_DIR)/bin/kinfly-sim-bench | tee $(REPO_ROOT)/out/bench/sim.json
	$(CODEC_BENCH) --tum $(TUM_SEQUENCE) | tee $(REPO_ROOT)/out/bench/codec.json
	$(MESH_BENCH) --tum $(TUM_SEQUENCE) | tee $(REPO_ROOT)/out/bench/mesh.json
	$(BUILD_DIR)/bin/kinfly-flight-bench | tee $(REPO_ROOT)/out/bench/flight.json
	$(PY) $(REPO_ROOT)/tests/bench/bench_flight_cost.py --build $(BUILD_DIR) --out $(REPO_ROOT)/out/bench
	$(BENCH_PY) $(REPO_ROOT)/tests/bench/bench_flight_oracle.py \
	  --flight-bench $(BUILD_DIR)/bin/kinfly-flight-bench --out $(REPO_ROOT)/out/bench
	$(PY) $(REPO_ROOT)/tests/bench/bench_link.py --data $(KINFLY_DATA) --out $(REPO_ROOT)/out/bench
	$(PY) $(REPO_ROOT)/tests/bench/bench_fw_link.py --out $(REPO_ROOT)/out/bench
	$(PY) $(REPO_ROOT)/tests/bench/bench_onboard.py --data $(KINFLY_DATA) --out $(REPO_ROOT)/out/bench \
	  --aarch64 $(AARCH64_DIR)
	$(PY) $(REPO_ROOT)/tests/bench/bench_ground.py --data $(KINFLY_DATA) --out $(REPO_ROOT)/out/bench
	OMP_NUM_THREADS=2 $(BENCH_PY) $(REPO_ROOT)/tests/bench/bench_vs_open3d.py --fuse $(FUSE) \
	  --data $(KINFLY_DATA) --out $(REPO_ROOT)/out/bench

# The sysroot is rebuilt only when scripts/aarch64-sysroot.sh (its package list) changes; test
# discovery and ctest run the arm64 binaries through qemu-aarch64 (the toolchain file's emulator).
firmware-aarch64: deps-aarch64
	$(REPO_ROOT)/scripts/aarch64-sysroot.sh $(AARCH64_SYSROOT)
	cmake -S $(REPO_ROOT) -B $(AARCH64_BUILD) -G Ninja -DCMAKE_BUILD_TYPE=Release \
	  -DCMAKE_TOOLCHAIN_FILE=$(REPO_ROOT)/cmake/aarch64-linux-gnu.cmake \
	  -DKINFLY_SYSROOT=$(AARCH64_SYSROOT)
	cmake --build $(AARCH64_BUILD) -j $(JOBS)

package-aarch64: firmware-aarch64
	rm -rf $(AARCH64_PKG)
	cd $(AARCH64_BUILD) && cpack -G DEB -B $(AARCH64_PKG)
	rm -rf $(AARCH64_PKG)/_CPack_Packages

BUILD_IMAGE = $(REPO_ROOT)/scripts/build-image.sh --deb $(AARCH64_DEB)
image: deps-image package-aarch64
	$(BUILD_IMAGE) --image $(BOARD)=$(IMAGE)

# The native build makes the replay's flight log and the trajectory the emulated one must match;
# pytest runs from .venv, whose kinfly-ground is the ground station in the loop.
# Under qemu the FusionPipeline's recovery scenarios (PipelineFixture: a covered second, a gap,
# a kidnapping, a new map; up to 135 synthetic 640x480 frames each, every lost one tried from
# several poses) took 1.5 to 7.5 minutes each, 23 of a CI run's 80 minutes; they run natively in
# `make test` and `make test-asan`. Under qemu stay the pipeline's tracking, lost-frame,
# given-pose, refinement and degenerate-wall scenarios, the relocaliser's own tests and the
# replays against the native build (docs/aarch64.md).
AARCH64_NATIVE_ONLY := PipelineFixture\.(ASecond|OnlyARealGap|LostFramesWithoutAPrior|AKidnapped|AfterEveryTryFails)
AARCH64_CTEST = ctest --test-dir $(AARCH64_BUILD) --output-on-failure -j $(JOBS) \
                -E '$(AARCH64_NATIVE_ONLY)'
# The unit tests under qemu run while the images are made (in the background, this Makefile being
# .NOTPARALLEL): that is mostly downloads and one dpkg at a time under emulation, so the two
# share two cores well (in a row they took 12 and 6 minutes of a CI run). Both boards' images
# share one root file system, made once. Either failing fails the target, once both have ended.
# The images are made in a session of their own, ended with the recipe: a background job ignores
# Ctrl-C, and mmdebstrap would go on as root without it.
test-aarch64: deps-demo deps-unit deps-image build package-aarch64 qemu-plugin
	setsid $(BUILD_IMAGE) --image uefi=$(AARCH64_DIR)/kinfly-uefi-arm64.img \
	  --image rpi4=$(AARCH64_DIR)/kinfly-rpi4-arm64.img & image=$$!; \
	  trap 'kill -TERM -- -$$image 2>/dev/null || true' EXIT; status=0; \
	  $(AARCH64_CTEST) || status=$$?; \
	  wait $$image || status=$$?; \
	  exit $$status
	$(PY) -m pytest $(REPO_ROOT)/tests -v -m aarch64

aarch64-unit-tests: firmware-aarch64
	$(AARCH64_CTEST)

# The QEMU plugin that counts the aarch64 build's instructions (make bench, its test in
# test-aarch64), built against the header of the installed qemu-user's source package, which
# is fetched from the Debian archive once (tests/bench/qemu_count.py: the standard library only,
# so the system's Python).
qemu-plugin: deps-aarch64
	python3 $(REPO_ROOT)/tests/bench/qemu_count.py $(AARCH64_DIR)/qemu-plugin

flash:
	@test -n "$(DEVICE)" || { echo "make flash IMAGE=... DEVICE=/dev/sdX CONFIRM=yes"; exit 2; }
	$(REPO_ROOT)/scripts/flash.sh --image $(IMAGE) --device $(DEVICE) \
	  $(if $(filter yes,$(CONFIRM)),--yes)

deploy:
	@test -n "$(HOST)" || { echo "make deploy HOST=user@drone"; exit 2; }
	$(REPO_ROOT)/scripts/deploy.sh --host $(HOST)

clean:
	rm -rf $(BUILD_DIR) $(ASAN_DIR) $(FUZZ_DIR) $(AARCH64_DIR) $(REPO_ROOT)/out

distclean: clean
	rm -rf $(REPO_ROOT)/.venv $(REPO_ROOT)/.venv-bench $(REPO_ROOT)/.venv-build
