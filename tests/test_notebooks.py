"""The guided notebooks: generated from their sources, and executed top to bottom headless.

Both versions of every notebook run in a real Jupyter kernel (nbclient,
ipykernel: the interpreter running the tests).  A failing cell fails the
test, except the student version's exercise stubs, tagged
``raises-exception`` by ``notebooks/build.py``.  Cells tagged
``needs-person`` (waiting on a click, a camera, a browser) are left out of
the run.  The solution versions' exercise checks assert geometric results
(a hull against the phantom's true volume, a camera centre against the one
the session was rendered with); the student versions must report
"not done yet" where a stub stands.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

import pytest

nbclient = pytest.importorskip("nbclient")
nbformat = pytest.importorskip("nbformat")
pytest.importorskip("jupytext")
pytest.importorskip("ipykernel")

ROOT = Path(__file__).resolve().parents[1]
NB = ROOT / "notebooks"
_spec = importlib.util.spec_from_file_location("notebooks_build", NB / "build.py")
build = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(build)

SOURCES = build.sources()


def _outputs_text(cell):
    parts = []
    for out in cell.get("outputs", []):
        if out.get("output_type") == "stream":
            parts.append(out.get("text", ""))
        elif out.get("output_type") == "error":
            parts.append(f"{out.get('ename')}: {out.get('evalue')}")
        else:
            parts.append(out.get("data", {}).get("text/plain", ""))
    return "".join(parts)


def _execute(nb, cwd, monkeypatch):
    nb = nbformat.from_dict(nb)
    nb.cells = [c for c in nb.cells if "needs-person" not in c.metadata.get("tags", [])]
    # the kernel is this interpreter (ipykernel's built-in spec) and imports this checkout's organlab
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p))
    monkeypatch.setenv("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    client = nbclient.NotebookClient(
        nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(cwd)}}, store_widget_state=True
    )
    client.execute()
    return nb


def test_sources_found():
    names = [p.stem for p in SOURCES]
    assert names[:4] == ["01_calibration", "02_background_and_silhouettes", "03_voxel_carving", "04_voxel_coloring"]
    assert names[4:] == ["05_surface_repair_and_measures", "06_live_capture"]


def test_written_notebooks_match_their_sources():
    """The committed .ipynb are what build.py makes of the sources, without outputs."""
    assert build.main(["--check"]) == 0


def test_build_splits_solutions():
    src = "x = 1\n    # BEGIN SOLUTION\n    y = x + 1\n    # END SOLUTION\n    # STUB: y = None\nprint(y)"
    sol, stu, raises = build.split_solution(src)
    assert sol == "x = 1\n    y = x + 1\nprint(y)"
    assert stu == "x = 1\n    y = None\nprint(y)"
    assert not raises
    sol, stu, raises = build.split_solution("# BEGIN SOLUTION\nz = 2\n# END SOLUTION")
    assert sol == "z = 2" and "NotImplementedError" in stu and raises
    with pytest.raises(build.BuildError):
        build.split_solution("# BEGIN SOLUTION\nz = 2")


@pytest.mark.slow
@pytest.mark.parametrize("version", build.VERSIONS)
@pytest.mark.parametrize("source", SOURCES, ids=[p.stem for p in SOURCES])
def test_notebook_executes(source, version, monkeypatch):
    nb = build.build_one(source)[version]
    n_exercises = sum("# BEGIN SOLUTION" in line for line in source.read_text().splitlines())
    assert n_exercises >= 2, f"{source.name}: every notebook ends with exercises"
    # executed where Jupyter would run it: next to the written notebook
    done = _execute(nb, build.target(version, source).parent, monkeypatch)
    text = "\n".join(_outputs_text(c) for c in done.cells if c.cell_type == "code")
    errors = [c for c in done.cells if any(o.get("output_type") == "error" for o in c.get("outputs", []))]
    pictures = sum(
        "image/png" in o.get("data", {}) for c in done.cells for o in c.get("outputs", [])
    )
    assert pictures >= 2, f"{source.name}: expected pictures, got {pictures}"
    # a widget's default values draw its picture: stored in its Output widget's state
    state = done.metadata.get("widgets", {}).get("application/vnd.jupyter.widget-state+json", {}).get("state", {})
    widget_pictures = [
        m for m in state.values()
        if m["model_name"] == "OutputModel" and any("image/png" in o.get("data", {}) for o in m["state"].get("outputs", []))
    ]
    if any("widget()" in c.source for c in done.cells if c.cell_type == "code"):
        assert widget_pictures, f"{source.name}: a widget drew no picture"
    key = [o for c in done.cells if "key-picture" in c.metadata.get("tags", []) for o in c.get("outputs", [])
           if "image/png" in o.get("data", {})]
    assert key, f"{source.name}: the cell tagged key-picture (docs/img) drew nothing"
    if version == "solutions":
        assert not errors
        assert text.count(": correct") == n_exercises, text
        assert "not done yet" not in text
    else:
        # a stub either says so or raises in a cell tagged to allow it
        assert all(build.RAISES in c.metadata.get("tags", []) for c in errors)
        assert text.count("not done yet") + len(errors) >= n_exercises, text
        assert ": correct" not in text
