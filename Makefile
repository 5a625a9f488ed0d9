# Quick start: `make demo`, `make test`.  Both create .venv from environment.txt when needed.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test venv bench clean sample

$(STAMP): environment.txt pyproject.toml
	@command -v $(PY) >/dev/null 2>&1 || { echo "error: $(PY) not found; install Python 3.11" >&2; exit 1; }
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -r environment.txt
	$(BIN)/python -m pip install --quiet --disable-pip-version-check --no-deps -e .
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
	$(BIN)/python -m organlab.synthetic sample_sessions/aaa_phantom --seed 0

clean:
	rm -rf $(VENV) demo_out
