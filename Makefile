# EgoSurg: the two commands a newcomer needs are `make demo` and `make test` (see README.md).
# Both create the virtual environment, install the system library open3d needs, and install the
# project with a CPU build of torch.

PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.egosurg-installed
# torch is pinned: an unpinned torch pulls a multi-GB CUDA build onto a CPU machine.
TORCH  := torch==2.13.0
PYTEST_MARKERS ?= not hardware and not gpu

.PHONY: demo test lint typecheck bench edge-check system-deps clean report-screenshot

demo: $(STAMP)
	$(BIN)/egosurg demo --out out/demo

# docs/report.png: the case report of the demo's case (docs/report.md) as headless Chromium
# shows it (the demo first, when out/demo has no report yet)
report-screenshot: $(STAMP)
	test -f out/demo/review/report.html || $(BIN)/egosurg demo --out out/demo
	$(BIN)/python bench/screenshot_report.py out/demo/review/report.html --out docs/report.png

test: $(STAMP)
	$(BIN)/python -m pytest -m "$(PYTEST_MARKERS)" $(PYTEST_ARGS)

lint: $(STAMP)
	$(BIN)/ruff check . && $(BIN)/ruff format --check .

# The edge packages (capture_agent, protocol) are checked again as Python 3.10, the Python of
# JetPack 6 on the nodes.
typecheck: $(STAMP)
	$(BIN)/mypy protocol sim capture_agent calibration reconstructor
	$(BIN)/mypy --python-version 3.10 capture_agent protocol

bench: $(STAMP)
	$(BIN)/python bench/bench_sim.py

# The edge as a node installs it (README, "Installing on the rig"): a clean Python 3.10 venv
# (JetPack 6's Python) with the base dependencies only, the node's commands, and the edge's tests
# that need no simulator, so a construct newer than 3.10 in the edge fails here. The files that
# build a simulated node (sim/ needs open3d and numba) run in `make test` only.
EDGE_PYTHON ?= $(shell for p in python3.10 "$$(pyenv prefix 3.10 2>/dev/null)/bin/python3.10"; do \
	"$$p" -c '' 2>/dev/null && { command -v "$$p"; break; }; done)
EDGE_VENV  := .venv-edge
EDGE_BIN   := $(EDGE_VENV)/bin
EDGE_STAMP := $(EDGE_VENV)/.egosurg-edge-installed
EDGE_WORK  := $(EDGE_VENV)/check
EDGE_TESTS := tests/test_edge_install.py tests/protocol/test_messages.py \
	tests/protocol/test_toml_config.py tests/protocol/test_command.py \
	tests/protocol/test_encode.py tests/protocol/test_intrinsics.py tests/protocol/test_session.py \
	tests/protocol/test_session_damage.py tests/capture_agent/test_config.py \
	tests/capture_agent/test_ptp.py tests/capture_agent/test_units.py \
	tests/protocol/test_sealing.py tests/protocol/test_sealing_keys.py \
	tests/protocol/test_session_sealed.py tests/protocol/test_session_sealed_chunks.py
# the one test of the session files that records through a simulated node
EDGE_SKIP  := tests/protocol/test_session_damage.py::test_a_recorder_killed_mid_take_resumes_into_a_linked_file

edge-check: $(EDGE_STAMP)
	rm -rf $(EDGE_WORK) && mkdir -p $(EDGE_WORK)
	$(EDGE_BIN)/egosurg agent --help >/dev/null
	$(EDGE_BIN)/egosurg recorder --help >/dev/null
	$(EDGE_BIN)/egosurg shell --help >/dev/null
	$(EDGE_BIN)/egosurg keys generate --out $(EDGE_WORK)/keys --name node
	$(EDGE_BIN)/egosurg keys show $(EDGE_WORK)/keys/node.key
	$(EDGE_BIN)/python -c "import pathlib, tests.protocol.test_session as t; \
		t._write_session(pathlib.Path('$(EDGE_WORK)/session.h5'))"
	$(EDGE_BIN)/egosurg session info $(EDGE_WORK)/session.h5
	$(EDGE_BIN)/python -m pytest -m "$(PYTEST_MARKERS) and not slow" $(EDGE_TESTS) \
		--deselect $(EDGE_SKIP) $(PYTEST_ARGS)

# libusb-1.0-0: open3d needs it at import. hdf5-tools: h5dump/h5ls/h5clear, to read sessions with
# the standard tools (and for the test that checks a session opens in h5dump). libfaketime: the
# fault test that steps one agent's clock (tests/e2e/test_faults.py; it skips without it).
# chromium: the headless browser of egosurg view's page test (tests/reconstructor/test_view.py;
# it skips without it). opencv-doc: OpenCV's samples hold the Middlebury Aloe stereo pair with its
# true disparity (bench/bench_stereo_real.py, tests/reconstructor/test_stereo_real.py; they skip
# without it).
system-deps:
	@if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' && command -v h5dump >/dev/null \
			&& ls /usr/lib/*/faketime/libfaketime.so.1 >/dev/null 2>&1 && command -v chromium >/dev/null \
			&& test -x /usr/sbin/ptp4l && test -f /usr/share/doc/opencv-doc/examples/data/aloeGT.png; then \
		echo "system: libusb-1.0-0, hdf5-tools, libfaketime, linuxptp, chromium and opencv-doc present"; \
	elif [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
		echo "system: installing libusb-1.0-0 (for open3d), hdf5-tools (h5dump), libfaketime, linuxptp (PTP), chromium and opencv-doc (tests)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 hdf5-tools libfaketime linuxptp \
			&& { DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium \
				|| echo "system: chromium not installed (optional: the browser test skips)"; } \
			&& { DEBIAN_FRONTEND=noninteractive apt-get install -y -qq opencv-doc \
				|| echo "system: opencv-doc not installed (optional: the Aloe stereo pair skips)"; }; \
	elif ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
		echo "system: hdf5-tools or linuxptp missing (optional: sudo apt-get install hdf5-tools linuxptp)"; \
	else \
		echo "open3d needs the system library libusb-1.0-0, which is missing."; \
		echo "Install it as root, then run make again:  sudo apt-get install libusb-1.0-0 hdf5-tools"; \
		exit 1; \
	fi

$(BIN)/python:
	@test -n "$(PYTHON)" || { echo "Python 3.11 is needed: install python3.11 and python3.11-venv"; exit 1; }
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else 1)' || \
		{ echo "EgoSurg needs Python 3.11; $(PYTHON) is $$($(PYTHON) --version)."; exit 1; }
	$(PYTHON) -m venv $(VENV)

# lpips is installed without its dependencies: its small linear heads are all EgoSurg uses, and
# its torchvision would pull another torch. EgoSurg builds the LPIPS backbone itself.
$(STAMP): pyproject.toml | $(BIN)/python system-deps
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q "$(TORCH)"
	$(BIN)/python -m pip install -q -e ".[workstation,dev,bench]"
	$(BIN)/python -m pip install -q --no-deps "lpips>=0.1.4"
	$(BIN)/python -c "import open3d, torch, cv2, zmq, h5py; print('installed: torch', torch.__version__, '| open3d', open3d.__version__)"
	@touch $(STAMP)

# The node's install is README's one command, `pip install -e .`; the test runner comes after it,
# and the list of what the node's install resolved is kept beside the venv.
$(EDGE_STAMP): pyproject.toml
	@test -n "$(EDGE_PYTHON)" || { echo "make edge-check needs Python 3.10 (JetPack 6's):" \
		"install python3.10 and python3.10-venv, or run 'pyenv install 3.10'"; exit 1; }
	rm -rf $(EDGE_VENV)
	$(EDGE_PYTHON) -m venv $(EDGE_VENV)
	$(EDGE_BIN)/python -m pip install -q --upgrade pip
	$(EDGE_BIN)/python -m pip install -q -e .
	$(EDGE_BIN)/python -m pip list --format=freeze --exclude pip --exclude setuptools \
		| tee $(EDGE_VENV)/edge-install.txt
	@echo "the edge install resolved $$(wc -l < $(EDGE_VENV)/edge-install.txt) packages"
	$(EDGE_BIN)/python -m pip install -q -e ".[test]"
	@touch $(EDGE_STAMP)

clean:
	rm -rf $(VENV) $(EDGE_VENV) out .pytest_cache
