# Everything a fresh machine needs: `make demo` runs the demo, `make test` the whole suite.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
PIP := $(BIN)/pip install --disable-pip-version-check -q -c constraints.txt
export MUJOCO_GL ?= osmesa
export PYOPENGL_PLATFORM ?= osmesa

# pytest-xdist workers for `make unit` (0: the suite in this process, serially; a file's tests stay on
# one worker: --dist loadfile). Two workers on 2 cores run it in 10:40-12:10 against 18-20 min serially,
# but 6 of 12 such runs (2026-11-29) failed a test, each on something real and fixed since: the tests'
# own timing (a Modbus peer's answer, a glove's swing, a fake chat server's race, the plan-preview test
# asking for a plan before its marker had a pose), the demo's force spike (the safety chain caught up
# too fast after its loop stalled) and, twice, a gripper alone letting go (its joint chain's stop
# command reached the gripper's joint). Serial stays the default until two-worker runs pass in a row.
TEST_WORKERS ?= 0

.PHONY: demo test lint typecheck unit bench soak proto clean sysdeps sysdeps-test markerless scene-js

$(VENV)/.installed: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --disable-pip-version-check -q --upgrade pip
	$(PIP) -e '.[dev]'
	$(PIP) --no-deps robosuite robosuite-models
	touch $@

# The MediaPipe tracker needs numpy<2 and protobuf<5, so it runs in its own venv as a
# separate process (see src/telerig/devices/markerless/); the tests run it for real.
.venv-markerless/.installed: src/telerig/devices/markerless/install.py
	$(BIN)/python -m telerig.devices.markerless.install --venv .venv-markerless
	touch $@

markerless: $(VENV)/.installed .venv-markerless/.installed

# The reference clients of the protocols our fake peers speak (ur_rtde, roslibpy, natnet, Unitree's SDK) live in
# their own venv; tests/reference_clients runs them against the fakes as subprocesses.
.venv-peers/.installed: tests/reference_clients/requirements.txt
	$(PYTHON) -m venv .venv-peers
	.venv-peers/bin/pip install --disable-pip-version-check -q -r tests/reference_clients/requirements.txt
	.venv-peers/bin/pip install --disable-pip-version-check -q --no-deps unitree_sdk2==1.0.1
	touch $@

# tensorflow-datasets (TensorFlow CPU) lives in its own venv: tests/export/test_rlds.py reads the RLDS
# export back with tfds.builder_from_directory in a subprocess; telerig itself writes RLDS without it.
.venv-tfds/.installed: tests/export/requirements-tfds.txt
	$(PYTHON) -m venv .venv-tfds
	.venv-tfds/bin/pip install --disable-pip-version-check -q -r tests/export/requirements-tfds.txt
	touch $@

# robomimic's dataset loader (needs torch, CPU) lives in its own venv: tests/export/test_robomimic.py loads
# the robomimic export with SequenceDataset in a subprocess. robomimic goes in --no-deps: it declares its
# training stack (tensorboard, egl_probe, diffusers), which the loader does not import.
.venv-robomimic/.installed: tests/export/requirements-robomimic.txt
	$(PYTHON) -m venv .venv-robomimic
	.venv-robomimic/bin/pip install --disable-pip-version-check -q -r tests/export/requirements-robomimic.txt
	.venv-robomimic/bin/pip install --disable-pip-version-check -q --no-deps robomimic==0.3.0
	touch $@

# three.js for the operator scene (telerig serve's /scene), pinned by package-lock.json and served from
# node_modules: nothing is fetched at run time; the page names this target when it is missing.
node_modules/.installed: package.json package-lock.json | sysdeps
	npm ci --no-audit --no-fund --ignore-scripts
	touch $@

scene-js: node_modules/.installed

sysdeps:
	./scripts/system-deps.sh

sysdeps-test:
	./scripts/system-deps.sh --test

demo: $(VENV)/.installed sysdeps node_modules/.installed
	$(BIN)/telerig demo

lint: $(VENV)/.installed
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/ruff format --check src tests benchmarks
	$(BIN)/lint-imports

typecheck: $(VENV)/.installed
	$(BIN)/mypy

unit: $(VENV)/.installed sysdeps-test node_modules/.installed .venv-markerless/.installed .venv-peers/.installed \
		.venv-tfds/.installed .venv-robomimic/.installed
	$(BIN)/pytest -q -n $(TEST_WORKERS) --dist loadfile

test: lint typecheck unit

# dex-retargeting (the hand-retargeting baseline) is a benchmark-only dependency in its own venv:
# it needs torch (CPU) and six, which it does not declare.
.venv-bench/.installed:
	$(PYTHON) -m venv .venv-bench
	.venv-bench/bin/pip install --disable-pip-version-check -q dex-retargeting==0.5.0 torch==2.13.0 six==1.17.0
	touch $@

bench: $(VENV)/.installed sysdeps-test .venv-bench/.installed
	$(BIN)/python benchmarks/latency.py
	$(BIN)/python benchmarks/latency_stages.py
	$(BIN)/python benchmarks/arm_ik.py
	$(BIN)/python benchmarks/safety_chain.py
	$(BIN)/python benchmarks/wire_codec.py
	$(BIN)/python benchmarks/hand_retarget.py
	$(BIN)/python benchmarks/control.py
	$(BIN)/python benchmarks/wbc_rig.py
	$(BIN)/python benchmarks/fleet.py
	$(BIN)/python benchmarks/dashboard.py
	$(BIN)/python benchmarks/scene.py
	$(BIN)/python benchmarks/robot_bridges.py
	$(BIN)/python benchmarks/ur_rtde.py
	$(BIN)/python benchmarks/fuzz_live_rig.py
	$(BIN)/python benchmarks/export.py
	$(BIN)/python benchmarks/qa_background.py

# The endurance runs for the note (80 min; want a quiet host): the demo rig for an hour, the fleet rig
# for 20 minutes; both run, and the target fails when either verdict does.
soak: $(VENV)/.installed sysdeps-test
	$(BIN)/python benchmarks/soak.py --rig demo --minutes 60 --plot benchmarks/results/soak_demo.png; \
	demo=$$?; \
	$(BIN)/python benchmarks/soak.py --rig fleet --minutes 20 --plot benchmarks/results/soak_fleet.png; \
	fleet=$$?; \
	test $$demo -eq 0 && test $$fleet -eq 0

proto: $(VENV)/.installed
	$(BIN)/python -m telerig.ir.protogen

clean:
	rm -rf $(VENV) node_modules .venv-markerless .venv-bench .venv-peers .venv-tfds .venv-robomimic .mypy_cache .ruff_cache .pytest_cache .import_linter_cache
