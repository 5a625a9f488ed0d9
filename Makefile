# Quick start: `make demo`, `make test`.  Both create .venv from environment.txt when needed.
# the first of the supported Pythons found (override with PY=...)
PY ?= $(or $(shell for p in python3.11 python3.12 python3.13; do command -v $$p >/dev/null 2>&1 && { echo $$p; break; }; done),python3.11)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test venv bench clean sample warm

# numba compiles organlab's kernels on their first call and keeps them in organlab/**/__pycache__:
# a fresh clone's first run compiled them (first `make demo`: carving 20 s against 0.4 s next time,
# a fresh viewer's first slider move 20 s).  `warm` fills that cache with every specialisation the
# default reconstruction, `make demo` and the viewer call, once, at install: the sample (true cameras,
# 4 mm; the kernels' signatures do not depend on the voxel size) reconstructed as `organlab reconstruct`
# does, then through one Engine as `organlab view` does: streamed view by view at its default 1 mm (the
# start-up: below 1.5 mm the view-by-view carving calls a kernel, kill_many, that coarser grids never
# reach), re-run at a chosen threshold (the slider), carved by view, the thesis hull, and the colouring
# methods of its Method menu (coloring, space_carving and photo compiled 35 CPU s on their first choice).
# Then the kernels only finer grids or the command reach, by their smallest calls (the same signatures, checked
# with numba's `.signatures`): the command's start-up loads (organlab.silhouette / organlab.poses warm_kernels:
# the median of more than 32 frames, the undistortion with the camera's read-only dist), the AAA route's 2 x 2 x 2 minima
# (_block_min, boxes over 50 000 voxels: 1 mm and finer), the AAA's coarse centreline voxels (sampler's _above_band:
# below 0.5 mm, where the centreline's voxel is 2 or more of the grid's; 1 mm and coarser read the voxels), and finishing's at 0.25 mm (near_deviation's
# _within, the sliver cut's check; _neighbour_mean's _star_sums; the fan count of an open surface, _fans_by_union,
# which the calibrating sample's 0.25 mm run reached).  Without them the old WARM left five kernels
# for a fresh clone's first 0.25 mm command to compile (the 1 mm `make demo` three of them, by numba's
# signatures and NUMBA_DEBUG_CACHE: the two start-up loads and _block_min).
# Checked on a fresh cache (NUMBA_CACHE_DIR, 2026-12-04): after it, `organlab reconstruct` of the sample
# (calibrating) at 0.25 mm and then at 1 mm writes no kernel; earlier, the viewer at 1 mm (start-up, slider
# moves, every method, carve by view) wrote none either.  It costs about 2 CPU minutes (121 s user, load 11).
WARM = $(BIN)/python -c "import shutil, tempfile; from organlab.pipeline import reconstruct; \
	from organlab.engine import Engine, Settings; from organlab.session import load_session; \
	from organlab.synthetic import with_true_cameras; d = tempfile.mkdtemp(); \
	s = load_session(with_true_cameras('sample_sessions/aaa_phantom', d + '/s')); r = reconstruct(s, voxel_size=4.0); \
	import numpy as np, organlab.silhouette as sil, organlab.poses as po; sil.warm_kernels(); po.warm_kernels(); \
	from organlab.surface._guard import near_deviation; from organlab.surface._aaa import _block_min; \
	from organlab.surface._remesh import _neighbour_mean; V, F = np.array(r.mesh.vertices), np.array(r.mesh.faces); \
	near_deviation(r.mesh, r.mesh, V[[0]], 4.0, voxel_size=4.0); _block_min(np.zeros((1, 1, 1))); _neighbour_mean(V, F); \
	from organlab.surface import measure_aaa; measure_aaa(r.field, r.grid, centreline_voxel_mm=8.0); \
	from organlab.surface._quality import nonmanifold_vertices; nonmanifold_vertices(type(r.mesh)(V, F[1:])); \
	e = Engine(s); st = Settings(voxel_size=4.0); e.stream_hull(st.replace(voxel_size=1.0), lambda *a: None); \
	e.carving_views(e.run(st.replace(threshold=20.0))); e.run(st.replace(hull='thesis')); \
	[e.run(st.replace(method=m)) for m in ('coloring', 'photo')]; shutil.rmtree(d)"

$(STAMP): environment.txt pyproject.toml
	@command -v $(PY) >/dev/null 2>&1 || { echo "error: $(PY) not found; install Python 3.11, 3.12 or 3.13 (or give PY=...)" >&2; exit 1; }
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -r environment.txt
	$(BIN)/python -m pip install --quiet --disable-pip-version-check --no-deps -e .
	@# OpenCV's sample chessboard photos (real calibration data with a published reference) for the tests
	@if [ ! -f /usr/share/doc/opencv-doc/examples/data/left01.jpg ] && command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends opencv-doc >/dev/null 2>&1 || { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends opencv-doc >/dev/null; } || echo "warning: opencv-doc not installed; tests/test_calibration_real.py will be skipped" >&2; fi
	@# Debian's chromium for the viewer's browser test (Playwright drives it; never 'playwright install')
	@if [ ! -x /usr/bin/chromium ] && command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium >/dev/null 2>&1 || { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium >/dev/null; } || echo "warning: chromium not installed; tests/test_viewer_browser.py will be skipped" >&2; fi
	@# gmsh's wheel links X11/OpenGL client libraries (no display is used): install them when missing
	@if ! ldconfig -p | grep -q libGLU.so.1 || ! ldconfig -p | grep -q libXcursor.so.1 || ! ldconfig -p | grep -q libXft.so.2 || ! ldconfig -p | grep -q libXinerama.so.1; then if command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends libglu1-mesa libxcursor1 libxft2 libxinerama1 libgomp1 >/dev/null || echo "warning: gmsh's libraries not installed; tetrahedral meshing will fail" >&2; else echo "warning: install libglu1-mesa libxcursor1 libxft2 libxinerama1 for gmsh" >&2; fi; fi
	@echo "compiling the numba kernels into their cache (once, about 1-2 min)"
	@$(WARM)
	@touch $(STAMP)

venv: $(STAMP)

warm: $(STAMP)
	$(WARM)

demo: $(STAMP)
	$(BIN)/organlab reconstruct sample_sessions/aaa_phantom --out demo_out --voxel-size 1 --picture

# The suite on TEST_WORKERS processes (pytest-xdist; the machine's 2 cores by default), each test file whole on one
# of them (--dist loadfile: a file's module fixtures are made once) but for the few long tests that share none
# (each notebook's run: tests/conftest.py's UNIT_SECONDS), the longest first (conftest's FILE_SECONDS;
# --no-loadscope-reorder keeps that order); it ends with the 15 slowest tests.  TEST_WORKERS=0 runs it in this process.
# Python's bytecode caches are written (__pycache__, git-ignored) even when the caller's environment sets
# PYTHONDONTWRITEBYTECODE: without them each worker re-ran pytest's assertion rewriting of every test module at
# collection (17.8 -> 9.3 CPU s per worker, collection alone) and each fresh process (notebook kernels, the
# command-line subprocesses) compiled the organlab modules it imports again (up to about 0.4 CPU s each).
TEST_WORKERS ?= 2

test: $(STAMP)
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest -q -p no:cacheprovider -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder --durations=15

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_carving.py

# Regenerate the bundled sample session (deterministic from its seed).
sample: $(STAMP)
	$(BIN)/python -m organlab.synthetic sample_sessions/aaa_phantom --seed 0 --no-camera --no-poses --force

# also drops numba's on-disk kernel cache (it does not notice edits of organlab/nbcam.py)
clean:
	rm -rf $(VENV) demo_out
	find organlab -name __pycache__ -type d -prune -exec rm -rf {} +
