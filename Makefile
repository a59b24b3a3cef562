# `make demo` and `make test` work on a fresh machine: they create .venv, install the CPU
# build of torch first (so pip never picks a multi-GB CUDA build), then the project.
VENV ?= .venv
PY := $(VENV)/bin/python
SUDO := $(shell [ "$$(id -u)" -eq 0 ] || echo sudo)
export PYOPENGL_PLATFORM := egl

.PHONY: demo test setup system-deps lint bench-fields bench-encodings gpu-check

$(VENV)/.installed: pyproject.toml
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $@

# Open3D needs libusb at import time; the viewer's browser tests need Chromium and its driver.
system-deps:
	@(ldconfig -p | grep -q 'libusb-1.0.so.0' && command -v chromium >/dev/null && command -v chromedriver >/dev/null) || \
	  ($(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq libusb-1.0-0 chromium chromium-driver)

setup: $(VENV)/.installed system-deps

# The end-to-end demo: 4-5 minutes on 2 CPU cores the first time (set-up included), about 2 with the cache
# (trained fields are reused from ~/.cache/regnf, or $$REGNF_CACHE).
demo: setup
	$(VENV)/bin/regnf demo --out out/demo

test: setup
	$(VENV)/bin/pytest -q

lint: setup
	$(VENV)/bin/ruff check .

# A benchmark's JSON in docs/results/ is what docs/benchmarks.md shows; `regnf bench page` remakes the page.
bench-fields: setup
	$(VENV)/bin/regnf bench fields --json docs/results/fields.json
	$(VENV)/bin/regnf bench page

bench-encodings: setup
	$(VENV)/bin/regnf bench encodings --json out/bench_encodings.json

# On a machine with a GPU: the tests marked `cuda` on the GPU, then the quick modes of the field,
# registration and render benchmarks there; one JSON and one table (layout: docs/benchmarks.md).
# Fails if a test or a benchmark does, after writing what it measured. GPU_DEVICE=cuda:1 picks a GPU.
GPU_DEVICE ?= cuda
gpu-check: setup
	mkdir -p out
	status=0; $(VENV)/bin/pytest -q -m cuda --device $(GPU_DEVICE) --junitxml out/gpu_check_tests.xml || status=$$?; \
	$(VENV)/bin/regnf bench gpu-check --device $(GPU_DEVICE) --tests out/gpu_check_tests.xml \
	  --json out/gpu_check.json --markdown out/gpu_check.md && exit $$status
