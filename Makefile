# Two commands for a newcomer: `make demo` and `make test`.
# Both create .venv when it is missing and install the project with all it needs.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup system-deps lint demo test test-all results results-quick bench docs clean

# Open3D's Linux wheel loads libusb-1.0 at import time.
system-deps:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing libusb-1.0-0 (needed by Open3D)"; \
	    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	  else \
	    echo "contactpose: Open3D needs the system library libusb-1.0-0; install it with: sudo apt-get install libusb-1.0-0" >&2; \
	  fi; \
	fi
	@# Headless Chromium for the test that opens the 3D view (it skips, saying why, without it).
	@if ! command -v chromium >/dev/null; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing chromium (the 3D view's browser test)"; \
	    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; \
	  else \
	    echo "contactpose: the 3D view's browser test needs Chromium: sudo apt-get install chromium" >&2; \
	  fi; \
	fi

$(STAMP): pyproject.toml
	@test -x $(PY) || python3 -m venv $(VENV)
	@echo "installing contactpose and its dependencies into $(VENV) (first run takes a few minutes)"
	@$(PY) -m pip install -q --disable-pip-version-check -e ".[test]" 2>&1 | grep -v "is ignored: it is neither a file nor a directory" || true
	@$(PY) -c "import contactpose, gtsam, emcee, trimesh, numba, dask.distributed" 
	@touch $(STAMP)

# Bytecode for the package's own modules, written even where PYTHONDONTWRITEBYTECODE is set
# (only what changed is compiled again): every command then starts 0.1 s sooner.
setup: system-deps $(STAMP)
	@$(PY) -m compileall -q contactpose >/dev/null

demo: setup
	$(PY) -m contactpose demo

lint: setup
	$(VENV)/bin/lint-imports --no-cache
	$(VENV)/bin/ruff check contactpose experiments tests

test: setup lint
	$(PY) -m pytest -q -m "not slow" -p no:cacheprovider --durations=15

test-all: setup lint
	$(PY) -m pytest -q -p no:cacheprovider --durations=15

# The docs site (mkdocs), built strictly: a broken reference or link fails.
docs: setup
	$(VENV)/bin/mkdocs build --strict --site-dir site

bench: setup
	$(PY) -m contactpose bench --out results/bench

results: setup
	$(PY) experiments/run_all.py

results-quick: setup
	$(PY) experiments/run_all.py --quick

clean:
	rm -rf $(VENV) build *.egg-info
