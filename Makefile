# Two commands do all the set-up on a fresh machine:
#   make demo   set-up, then the main job on built-in synthetic data
#   make test   set-up, then the test suite
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
SETUP_STAMP := $(VENV)/.setup-$(shell cat pyproject.toml Makefile | sha1sum | cut -c1-12)
DEMO_DATA ?= demo-data
DEMO_OUT ?= demo-out
WORKERS ?= 2
MEDIAPIPE_VERSION := 0.10.21
MODELS_DIR := .cache/models/mediapipe-$(MEDIAPIPE_VERSION)

.PHONY: setup browser demo demo-oracle demo-bundled test bench clean

setup: $(SETUP_STAMP)

$(SETUP_STAMP): pyproject.toml Makefile
	@command -v python3 >/dev/null || { echo "python3 (3.11) is required"; exit 1; }
	@# open3d's wheel links libusb-1.0; install it where missing (needs root or sudo).
	@if ! ldconfig -p | grep -q 'libusb-1.0.so.0'; then \
	  echo "installing libusb-1.0-0 (needed by open3d)"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq libusb-1.0-0; \
	fi
	@[ -x $(PY) ] || python3 -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	@# torch first: the CPU build of 2.13.0; anything else would pull GBs of CUDA wheels.
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e '.[dev,cluster,models,viz]'
	@# nuscenes-devkit pins numpy<2: test dependency, installed without its pins.
	$(PIP) install -q --no-deps nuscenes-devkit==1.2.0
	@# the bundled BlazePose models (Apache-2.0): the mediapipe wheel is fetched once (not
	@# installed: it pins numpy<2) and only its .tflite files kept, checked by sha256
	@if [ ! -f $(MODELS_DIR)/pose_landmark_full.tflite ] || [ ! -f $(MODELS_DIR)/pose_detection.tflite ]; then \
	  tmp=$$(mktemp -d) && \
	  $(PIP) download -q --no-deps --only-binary=:all: --python-version 3.11 --platform manylinux_2_28_x86_64 \
	    -d $$tmp mediapipe==$(MEDIAPIPE_VERSION) && \
	  $(VENV)/bin/mobileocc models unpack-bundled --wheel $$tmp/mediapipe-$(MEDIAPIPE_VERSION)-*.whl \
	    --cache $(MODELS_DIR) && \
	  rm -rf $$tmp; \
	fi
	@rm -f $(VENV)/.setup-*; touch $@

# the default (real) path on the simulated data: no ground truth read; the report scores it
# against the simulator's truth
demo: setup
	$(VENV)/bin/mobileocc demo --data $(DEMO_DATA) --out $(DEMO_OUT) --workers $(WORKERS)

# the simulator's oracle (perception and the fit's start from gt/ + noise)
demo-oracle: setup
	$(VENV)/bin/mobileocc demo --config configs/oracle.yaml --data $(DEMO_DATA) \
	  --out $(DEMO_OUT)-oracle --workers $(WORKERS)

# BlazePose keypoints and masks with the oracle's semantics and start
demo-bundled: setup
	$(VENV)/bin/mobileocc demo --config configs/bundled-models.yaml --data $(DEMO_DATA) \
	  --out $(DEMO_OUT)-bundled --workers $(WORKERS)

# headless Chromium for the viewer's browser tests (tests/test_viewer.py), installed where
# missing (root or passwordless sudo); where it cannot be, those tests skip and say why
browser:
	@if ! command -v chromium >/dev/null && ! command -v chromium-browser >/dev/null; then \
	  echo "installing chromium (the viewer's browser tests)"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo "sudo -n" ); \
	  { $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq chromium; } \
	    || echo "chromium could not be installed: the viewer's browser tests will be skipped"; \
	fi

test: setup browser
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(PY) -m pytest -q -n 2 --dist loadgroup

bench: setup
	$(VENV)/bin/mobileocc bench --quick --json bench.json

clean:
	rm -rf $(DEMO_DATA) $(DEMO_OUT) .pytest_cache
