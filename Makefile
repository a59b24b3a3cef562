# `make demo` and `make test` work on a fresh machine: they create .venv, install the CPU
# build of torch first (so pip never picks a multi-GB CUDA build), then the project.
VENV ?= .venv
PY := $(VENV)/bin/python
SUDO := $(shell [ "$$(id -u)" -eq 0 ] || echo sudo)
export PYOPENGL_PLATFORM := egl

.PHONY: demo test setup system-deps lint bench-fields bench-encodings

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

# The end-to-end demo: about 10 minutes on 2 CPU cores the first time, about 3 with the cache
# (trained fields are reused from ~/.cache/regnf, or $$REGNF_CACHE).
demo: setup
	$(VENV)/bin/regnf demo --out out/demo

test: setup
	$(VENV)/bin/pytest -q

lint: setup
	$(VENV)/bin/ruff check .

bench-fields: setup
	$(VENV)/bin/regnf bench fields --json out/bench_fields.json --markdown docs/benchmarks_fields.md

bench-encodings: setup
	$(VENV)/bin/regnf bench encodings --json out/bench_encodings.json
