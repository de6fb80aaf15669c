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

.PHONY: demo test lint typecheck bench system-deps clean

demo: $(STAMP)
	$(BIN)/egosurg demo --out out/demo

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

# libusb-1.0-0: open3d needs it at import. hdf5-tools: h5dump/h5ls/h5clear, to read sessions with
# the standard tools (and for the test that checks a session opens in h5dump). libfaketime: the
# fault test that steps one agent's clock (tests/e2e/test_faults.py; it skips without it).
# chromium: the headless browser of egosurg view's page test (tests/reconstructor/test_view.py;
# it skips without it).
system-deps:
	@if ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' && command -v h5dump >/dev/null \
			&& ls /usr/lib/*/faketime/libfaketime.so.1 >/dev/null 2>&1 && command -v chromium >/dev/null \
			&& test -x /usr/sbin/ptp4l; then \
		echo "system: libusb-1.0-0, hdf5-tools, libfaketime, linuxptp and chromium present"; \
	elif [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
		echo "system: installing libusb-1.0-0 (for open3d), hdf5-tools (h5dump), libfaketime, linuxptp (PTP) and chromium (tests)"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 hdf5-tools libfaketime linuxptp \
			&& { DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium \
				|| echo "system: chromium not installed (optional: the browser test skips)"; }; \
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
	$(BIN)/python -m pip install -q -e ".[dev,bench]"
	$(BIN)/python -m pip install -q --no-deps "lpips>=0.1.4"
	$(BIN)/python -c "import open3d, torch, cv2, zmq, h5py; print('installed: torch', torch.__version__, '| open3d', open3d.__version__)"
	@touch $(STAMP)

clean:
	rm -rf $(VENV) out .pytest_cache
