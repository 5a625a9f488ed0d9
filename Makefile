# Quick start: `make demo`, `make test`.  Both create .venv from environment.txt when needed.
# the first of the supported Pythons found (override with PY=...)
PY ?= $(or $(shell for p in python3.11 python3.12 python3.13; do command -v $$p >/dev/null 2>&1 && { echo $$p; break; }; done),python3.11)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test venv bench clean sample

$(STAMP): environment.txt pyproject.toml
	@command -v $(PY) >/dev/null 2>&1 || { echo "error: $(PY) not found; install Python 3.11, 3.12 or 3.13 (or give PY=...)" >&2; exit 1; }
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -r environment.txt
	$(BIN)/python -m pip install --quiet --disable-pip-version-check --no-deps -e .
	@# OpenCV's sample chessboard photos (real calibration data with a published reference) for the tests
	@if [ ! -f /usr/share/doc/opencv-doc/examples/data/left01.jpg ] && command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends opencv-doc >/dev/null 2>&1 || { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends opencv-doc >/dev/null; } || echo "warning: opencv-doc not installed; tests/test_calibration_real.py will be skipped" >&2; fi
	@touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/organlab reconstruct sample_sessions/aaa_phantom --out demo_out --voxel-size 1 --picture

test: $(STAMP)
	$(BIN)/python -m pytest -q -p no:cacheprovider

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_carving.py

# Regenerate the bundled sample session (deterministic from its seed).
sample: $(STAMP)
	$(BIN)/python -m organlab.synthetic sample_sessions/aaa_phantom --seed 0 --no-camera --no-poses --force

# also drops numba's on-disk kernel cache (it does not notice edits of organlab/_nbcam.py)
clean:
	rm -rf $(VENV) demo_out
	find organlab -name __pycache__ -type d -prune -exec rm -rf {} +
