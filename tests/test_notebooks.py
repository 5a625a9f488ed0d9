"""The guided notebooks: generated from their sources, and executed top to bottom headless.

Both versions of every notebook run in a real Jupyter kernel (nbclient,
ipykernel: the interpreter running the tests).  A failing cell fails the
test, except the student version's exercise stubs, tagged
``raises-exception`` by ``notebooks/build.py`` (JupyterLab's Run All goes
on past them too).  Every cell runs, as under Run All: a cell that needs a
real rig runs only when the notebook's flag says one is attached
(``RIG_ATTACHED = False`` at the top of 06), and prints that it did not.
The solution versions' exercise checks assert geometric results
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
    # the kernel is this interpreter (ipykernel's built-in spec) and imports this checkout's organlab
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p))
    monkeypatch.setenv("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    client = build.notebook_client(nb, cwd, timeout=300, store_widget_state=True)
    client.execute()
    return nb


def test_sources_found():
    names = [p.stem for p in SOURCES]
    assert names[:4] == ["01_calibration", "02_background_and_silhouettes", "03_voxel_carving", "04_voxel_coloring"]
    assert names[4:] == ["05_surface_repair_and_measures", "06_live_capture"]


def test_written_notebooks_match_their_sources():
    """The committed .ipynb are what build.py makes of the sources, without outputs."""
    assert build.main(["--check"]) == 0


def _copy_notebooks(tmp_path):
    import shutil

    root = tmp_path / "notebooks"
    for sub in ("src", *build.VERSIONS):
        shutil.copytree(NB / sub, root / sub)
    return root


def _autosave_as_jupyterlab(path):
    """Rewrite a notebook as JupyterLab 4 does when it opens, runs and autosaves it (no edit of a cell)."""
    import json

    doc = json.loads(path.read_text())
    doc["metadata"]["kernelspec"] = {"display_name": "Python 3 (ipykernel)", "language": "python", "name": "python3"}
    doc["metadata"]["language_info"] = {
        "codemirror_mode": {"name": "ipython", "version": 3}, "file_extension": ".py", "mimetype": "text/x-python",
        "name": "python", "nbconvert_exporter": "python", "pygments_lexer": "ipython3", "version": "3.11.2",
    }
    doc["metadata"]["widgets"] = {"application/vnd.jupyter.widget-state+json": {
        "state": {"0f3a": {"model_module": "@jupyter-widgets/controls", "model_module_version": "2.0.0",
                           "model_name": "FloatSliderModel", "state": {"value": 41.0}}},
        "version_major": 2, "version_minor": 0}}
    for n, cell in enumerate(doc["cells"]):
        cell["metadata"].update({"trusted": True, "scrolled": True, "jupyter": {"source_hidden": False}})
        if cell["cell_type"] == "code":
            cell["execution_count"] = n + 1
            cell["metadata"]["execution"] = {"iopub.execute_input": "2026-12-01T20:00:00.000Z"}
            cell["outputs"] = [{"name": "stdout", "output_type": "stream", "text": ["ran\n"]}]
    # JupyterLab writes one JSON line per source line, indent 1, and keeps unknown metadata (organlab's digest)
    path.write_text(json.dumps(doc, indent=1, ensure_ascii=False) + "\n")


def test_jupyterlab_autosave_keeps_the_notebooks_fresh(tmp_path, capsys):
    """Opening, running and autosaving a student notebook is not an edit: the freshness check still passes."""
    root = _copy_notebooks(tmp_path)
    nb_path = root / "student" / "01_calibration.ipynb"
    before = nb_path.read_text()
    _autosave_as_jupyterlab(nb_path)
    assert nb_path.read_text() != before
    assert build.freshen(root, check=True) == 0, capsys.readouterr().err
    # a student's answer in an exercise cell is an edit: reported, and neither a check nor a build overwrites it
    doc = nbformat.read(nb_path, as_version=4)
    k = next(i for i, c in enumerate(doc.cells) if "rms_05 = None" in c.source)
    doc.cells[k].source = doc.cells[k].source.replace("rms_05 = None  # your code here", "rms_05 = 0.04  # my answer")
    nbformat.write(doc, nb_path)
    mine = nb_path.read_text()
    assert build.freshen(root, check=True) == 1
    err = capsys.readouterr().err
    assert f"student/01_calibration.ipynb (cell {k + 1} (source))" in err and "never overwrites" in err
    assert "run python notebooks/build.py" not in err
    assert build.freshen(root, say=lambda _m: None) == 1  # a plain build leaves the student's work alone
    assert nb_path.read_text() == mine
    # a changed source with an untouched notebook is stale, and a build rewrites it
    src = root / "src" / "02_background_and_silhouettes.py"
    src.write_text(src.read_text().replace("# %% [markdown]\n", "# %% [markdown]\n# A new first line.\n#\n", 1))
    assert build.freshen(root, check=True) == 1
    assert "out of date with its source" in capsys.readouterr().err
    build.freshen(root, say=lambda _m: None)
    assert "A new first line." in (root / "solutions" / "02_background_and_silhouettes.ipynb").read_text()
    assert nb_path.read_text() == mine
    assert build.freshen(root, check=True, force=True) == 1 and build.freshen(root, force=True, say=print) == 0
    assert "rms_05 = 0.04" not in nb_path.read_text()


def test_build_refuses_cells_left_out_of_run_all(tmp_path):
    src = tmp_path / "09_rig.py"
    src.write_text('# %% [markdown]\n# A rig.\n\n# %% tags=["needs-person"]\nopen("/dev/ttyUSB0")\n')
    with pytest.raises(build.BuildError, match="RIG_ATTACHED"):
        build.build_one(src)


def test_checkpoints_are_ignored():
    assert ".ipynb_checkpoints/" in (ROOT / ".gitignore").read_text().splitlines()


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
    # every code cell ran, in order (Run All): none skipped, none left out
    counts = [c.get("execution_count") for c in done.cells if c.cell_type == "code"]
    assert counts == list(range(1, len(counts) + 1)), counts
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
    if "RIG_ATTACHED = False" in source.read_text():
        assert "RIG_ATTACHED is False: no real-rig capture" in text, text
    if version == "solutions":
        assert not errors
        assert text.count(": correct") == n_exercises, text
        assert "not done yet" not in text
    else:
        # a stub either says so or raises in a cell tagged to allow it
        assert all(build.RAISES in c.metadata.get("tags", []) for c in errors)
        assert text.count("not done yet") + len(errors) >= n_exercises, text
        assert ": correct" not in text


@pytest.mark.slow
def test_calibration_exercise_survives_a_click_between_cells(monkeypatch):
    """Under Run All the kernel handles a widget's click between two cells: notebook 01's exercise 1 is
    checked against the fit that click cannot change (``checker.baseline``).  Checked against
    ``checker.calibration``, as it was, a click on "drop this image" between the exercise and its check
    refits it under the student's answer and the check fails (an AssertionError: one run in several)."""
    source = next(p for p in SOURCES if p.stem.startswith("01_"))
    nb = build.build_one(source)["solutions"]
    k = next(i for i, c in enumerate(nb.cells) if c.cell_type == "code" and "rms_05 = float" in c.source)
    click = nbformat.v4.new_code_cell(
        "checker.controls['drop'].click()  # a person's click on the selected (worst) image\n"
        "assert checker.calibration is not checker.baseline and checker.dropped == (worst,)\n"
        "print('clicked: refitted without', worst)")
    nb.cells = nb.cells[:k + 1] + [click, nb.cells[k + 1]]  # up to exercise 1's check
    done = _execute(nb, build.target("solutions", source).parent, monkeypatch)
    text = "\n".join(_outputs_text(c) for c in done.cells if c.cell_type == "code")
    assert "clicked: refitted without" in text and "Exercise 1: correct" in text, text
