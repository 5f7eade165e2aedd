# Fettle - the commands in the README. Each installs missing Debian packages first
# (scripts/install-deps), configures, builds and runs.
BUILD_DIR ?= build
BUILD_TYPE ?= RelWithDebInfo
JOBS ?= $(shell nproc)
CMAKE_ARGS ?=
# Sanitizer and fuzz builds live in their own directories (docs/development.md).
ASAN_BUILD_DIR ?= build-asan
FUZZ_BUILD_DIR ?= build-fuzz
FUZZ_SECONDS ?= 300
SOAK_CYCLES ?= 500
SOAK_FAULT_RATE ?= 0.3
# ctest arguments for test-asan, e.g. ASAN_CTEST_ARGS="-LE slow".
ASAN_CTEST_ARGS ?=
# Targets test-asan builds; empty: every target, so every test runs.
ASAN_TARGETS ?=

.PHONY: all deps configure build test test-unit test-asan test-asan-ci test-tsan fuzz soak demo bench accuracy accuracy-scan accuracy-bias accuracy-vision robustness clean

all: build

deps:
	@scripts/install-deps

$(BUILD_DIR)/build.ninja:
	cmake -S . -B $(BUILD_DIR) -G Ninja -DCMAKE_BUILD_TYPE=$(BUILD_TYPE) $(CMAKE_ARGS)

configure: deps $(BUILD_DIR)/build.ninja

build: configure
	cmake --build $(BUILD_DIR) -j $(JOBS)

# All tests (unit, integration, slow).
test: build
	cd $(BUILD_DIR) && ctest --output-on-failure -j $(JOBS) --timeout 600

# Only the fast unit tests.
test-unit: build
	cd $(BUILD_DIR) && ctest --output-on-failure -j $(JOBS) -L unit

# Every test under AddressSanitizer + UndefinedBehaviorSanitizer (clang, build-asan). -O1 with
# line tables only: it builds in about the time of the plain build (gcc -O2 -g with ASan takes
# four times as long for vision's PCL-heavy files), and stack traces still name file and line.
ASAN_FLAGS = -O1 -gline-tables-only -DNDEBUG
# The recipe caches the plain build's slow tests left in $(BUILD_DIR)/test-cache (the planner's
# grid: 45 s to build with gcc -O2, about 2 min under ASan; the pipeline test's vision template) seed
# a sanitizer build's: each test's store whole, where the sanitizer build has none. Each cache
# is keyed by its inputs, so a stale one is rebuilt; the code that builds them is tested under
# the sanitizers on its own.
SEED_TEST_CACHE = scripts/seed-test-cache $(BUILD_DIR)
test-asan: deps
	CC=clang CXX=clang++ cmake -S . -B $(ASAN_BUILD_DIR) -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
	      -DCMAKE_C_FLAGS_RELWITHDEBINFO="$(ASAN_FLAGS)" -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="$(ASAN_FLAGS)" \
	      -DFETTLE_SANITIZE=address,undefined -DFETTLE_BUILD_BENCH=OFF $(CMAKE_ARGS)
	cmake --build $(ASAN_BUILD_DIR) -j $(JOBS) $(if $(strip $(ASAN_TARGETS)),--target $(ASAN_TARGETS))
	$(SEED_TEST_CACHE) $(ASAN_BUILD_DIR)
	cd $(ASAN_BUILD_DIR) && ASAN_OPTIONS=$${ASAN_OPTIONS:-detect_leaks=1} UBSAN_OPTIONS=$${UBSAN_OPTIONS:-print_stacktrace=1} \
	  ctest --output-on-failure -j $(JOBS) --timeout 900 $(ASAN_CTEST_ARGS)

# What CI runs under ASan + UBSan in its time budget (docs/development.md, "CI"): the tests of
# core, config, the device links (PLC, camera, robot, spindle) and the simulated devices, whole:
# the code that talks to the cell's hardware, and all of it that builds without vision's and
# planning's PCL-heavy sources (a third of the full ASan build). Only their targets are built,
# so ctest leaves out the placeholders of the rest (<target>_NOT_BUILT), the soak (fettled) and
# the fuzz replays (make fuzz runs every fuzz target under ASan + UBSan). Tests that run
# fettle-sim (the spindle over socketcand, the camera CLI) need the whole build and are left
# to `make test-asan`, which runs every test.
ASAN_CI_TARGETS = test_core test_config test_config_bad_input test_calibration_file \
                  test_camera_decode test_camera_bad_input test_camera_sim test_camera_interop \
                  test_plc_codec test_plc_link test_plc_bad_input \
                  test_robot_protocol test_robot_link test_robot_bad_input \
                  test_spindle_canopen \
                  test_sim_geometry test_sim_scanner test_sim_grind test_sim_sockets test_sim_errors
test-asan-ci:
	$(MAKE) test-asan ASAN_TARGETS="$(ASAN_CI_TARGETS)" ASAN_CTEST_ARGS="-E '_NOT_BUILT|^soak_|^fuzz_replay[.]'"

# The concurrency tests (ctest label "concurrency": device links, control socket, fettled)
# under ThreadSanitizer (clang, build-tsan); TSAN_CTEST_ARGS adds ctest arguments.
TSAN_BUILD_DIR ?= build-tsan
TSAN_CTEST_ARGS ?=
# Only what the concurrency tests run is built (the whole tree under TSan takes far longer).
TSAN_TARGETS = test_robot_link test_plc_link test_spindle_canopen test_spindle_socketcand test_camera_sim \
               test_control test_fettled fettled fettle-sim fettle
# The suppressions are needed while building too: gtest's test discovery runs the programs.
TSAN_DEFAULT_OPTIONS = halt_on_error=1:second_deadlock_stack=1:suppressions=$(CURDIR)/tests/sanitizers/tsan.supp
test-tsan: deps
	CC=clang CXX=clang++ cmake -S . -B $(TSAN_BUILD_DIR) -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
	      -DCMAKE_C_FLAGS_RELWITHDEBINFO="$(ASAN_FLAGS)" -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="$(ASAN_FLAGS)" \
	      -DFETTLE_SANITIZE=thread -DFETTLE_BUILD_BENCH=OFF $(CMAKE_ARGS)
	TSAN_OPTIONS=$${TSAN_OPTIONS:-$(TSAN_DEFAULT_OPTIONS)} cmake --build $(TSAN_BUILD_DIR) -j $(JOBS) --target $(TSAN_TARGETS)
	$(SEED_TEST_CACHE) $(TSAN_BUILD_DIR)
	cd $(TSAN_BUILD_DIR) && TSAN_OPTIONS=$${TSAN_OPTIONS:-$(TSAN_DEFAULT_OPTIONS)} \
	  ctest --output-on-failure -j $(JOBS) --timeout 1800 -L concurrency $(TSAN_CTEST_ARGS)

# libFuzzer targets (clang, build-fuzz), FUZZ_SECONDS each; fails on any crash.
fuzz: deps
	CC=clang CXX=clang++ cmake -S . -B $(FUZZ_BUILD_DIR) -G Ninja -DCMAKE_BUILD_TYPE=$(BUILD_TYPE) -DFETTLE_FUZZ=ON \
	      -DFETTLE_BUILD_BENCH=OFF $(CMAKE_ARGS)
	cmake --build $(FUZZ_BUILD_DIR) -j $(JOBS) --target fuzzers
	tests/fuzz/run $(FUZZ_BUILD_DIR) $(FUZZ_SECONDS)

# fettled through SOAK_CYCLES cycles on the simulated cell with random device faults
# (fettle-sim soak; ~5 s a cycle on 2 cores). Results in $(BUILD_DIR)/soak/soak.json; the
# run's summary.md goes into docs/results.md, pass or fail.
soak: build
	rm -f $(BUILD_DIR)/soak/summary.md
	$(BUILD_DIR)/bin/fettle-sim soak --config config/cell.sim.toml --cycles $(SOAK_CYCLES) \
	  --fault-rate $(SOAK_FAULT_RATE) --out $(BUILD_DIR)/soak; status=$$?; \
	  scripts/update-results soak $(BUILD_DIR)/soak/summary.md && exit $$status

demo: build
	@scripts/demo $(BUILD_DIR)

bench: build
	@scripts/bench $(BUILD_DIR)

# Closed-loop accuracy on 50 simulated castings (scan, plan, grind, re-scan, evaluate; the
# paper's Table 1/2): fettle-sim trial. The castings are drawn when it runs (ACCURACY_SEEDS,
# random:50: 50 consecutive seeds from a start above 1000, printed first so the run can be
# repeated with ACCURACY_SEEDS=A-B); it fails on any gouge deeper than 0.10 mm anywhere on the
# part. Results in $(BUILD_DIR)/accuracy/.
# The run's summary.md goes into docs/results.md, pass or fail. ERRORS=config/sim/errors-realistic.toml
# runs it in a world with a real cell's errors (docs/simulator.md, "Error budget"), into its own
# section; CELL_SEED draws that cell's calibration and robot errors (default random: drawn when it
# runs and printed, like the castings; the summary names it).
ACCURACY_SEEDS ?= random:50
ERRORS ?=
CELL_SEED ?= random
accuracy: build
	rm -f $(BUILD_DIR)/accuracy/summary.md
	$(BUILD_DIR)/bin/fettle-sim trial --part config/parts/pump-body.toml --cell config/cell.sim.toml \
	  --seeds $(ACCURACY_SEEDS) $(if $(ERRORS),--errors $(ERRORS)) $(if $(CELL_SEED),--cell-seed $(CELL_SEED)) \
	  --out $(BUILD_DIR)/accuracy; status=$$?; \
	  scripts/update-results $(if $(ERRORS),accuracy-errors,accuracy) $(BUILD_DIR)/accuracy/summary.md && exit $$status

# The same closed loop with a template built from a golden casting's scan ([template] source =
# "scan", `fettle template build`) instead of the simulator's exact model (scripts/accuracy-scan-template;
# GOLDEN_SEED draws the golden casting, ERRORS and CELL_SEED as above). Into docs/results.md.
accuracy-scan: build
	@ACCURACY_SEEDS='$(ACCURACY_SEEDS)' ERRORS='$(ERRORS)' CELL_SEED='$(CELL_SEED)' scripts/accuracy-scan-template $(BUILD_DIR)

# Which error of a real cell matters most: each source of config/sim/errors-realistic.toml alone,
# 0 to 2x its size (ROBUSTNESS_STEPS), on castings drawn once at run time (ROBUSTNESS_SEEDS);
# a table into docs/results.md and docs/images/robustness.png (scripts/robustness). By hand: the
# default sweep grinds about 460 castings (4 hours on the 2-core machine).
robustness: build
	@scripts/robustness $(BUILD_DIR)

# The cell's verification against gouges made on purpose: the executed path 0.4 mm below the
# commanded one on castings drawn when it runs (BIAS_SEEDS); every casting the simulator finds
# gouged deeper than gouge_depth_mm must read NOK with the gouge's place. Writes its section of
# docs/results.md.
BIAS_SEEDS ?= random:5
# --no-learning: this checks the verification on castings that are all gouged; with the cell
# learning its bias (docs/compensation.md) only the first one would be.
accuracy-bias: build
	rm -f $(BUILD_DIR)/accuracy-bias/summary.md
	$(BUILD_DIR)/bin/fettle-sim trial --part config/parts/pump-body.toml --cell config/cell.sim.toml \
	  --seeds $(BIAS_SEEDS) --path-bias-mm 0 0 -0.4 --no-learning --out $(BUILD_DIR)/accuracy-bias; status=$$?; \
	  scripts/update-results accuracy-bias $(BUILD_DIR)/accuracy-bias/summary.md && exit $$status

# The vision accuracy test of issue 4 on 50 simulated castings (ctest runs it too).
accuracy-vision: build
	FETTLE_ACCURACY_SEEDS=50 $(BUILD_DIR)/bin/test_vision_sim_accuracy --gtest_filter='VisionSimAccuracy.Seeded*'

clean:
	rm -rf $(BUILD_DIR)
