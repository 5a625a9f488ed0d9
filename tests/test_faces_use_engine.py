"""The faces (viewer, widgets, capture viewer) call the engine: no stage function is used in them directly.

Parsed, not imported: every module of organlab/viewer and organlab/widgets is
read with ``ast``; a face that imports a stage function, or calls one as an
attribute of a module (``carving.hull_field(...)``), fails with the file and line.
"""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "organlab"
FACES = sorted([*ROOT.glob("viewer/*.py"), *ROOT.glob("widgets/*.py")])

#: The reconstruction's stage functions: only organlab.engine runs them.
STAGE_FUNCTIONS = {
    "calibration_for", "session_cameras",
    "silhouettes", "silhouette", "session_silhouettes", "background_model", "background_noise", "difference",
    "SilhouetteModel",
    "carve", "hull_field", "ProgressiveCarver", "carving_views",
    "color_voxels", "voxel_colors",
    "mesh_from_field", "mesh_from_volume", "color_vertices", "finish_surface", "measure_aaa", "measure",
    "view_agreement", "render_silhouette", "pixel_footprint", "reconstruct",
}

#: Modules whose names are stage functions when called through the module (``carving.carve``).
STAGE_MODULES = {"calibration", "silhouette", "carving", "coloring", "surface", "agreement", "pipeline", "datasets"}


def _violations(path):
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            for alias in node.names:
                if alias.name in STAGE_FUNCTIONS:
                    found.append((node.lineno, f"imports {alias.name} from {'.' * node.level}{node.module or ''}"))
        elif isinstance(node, ast.Attribute) and node.attr in STAGE_FUNCTIONS:
            base = node.value
            if isinstance(base, ast.Name) and base.id in STAGE_MODULES:
                found.append((node.lineno, f"calls {base.id}.{node.attr}"))
    return sorted(found)


def test_the_check_finds_stage_logic():
    """The check itself: what the viewer held before issue 19 is found."""
    src = ("from ..carving import hull_field\nfrom .. import coloring\n"
           "def f():\n    coloring.color_voxels()\n    from ..surface import finish_surface, Mesh\n")
    tmp = Path(__file__).with_name("_face_probe.py")
    try:
        tmp.write_text(src)
        got = [what for _, what in _violations(tmp)]
    finally:
        tmp.unlink()
    assert got == ["imports hull_field from ..carving", "calls coloring.color_voxels",
                   "imports finish_surface from ..surface"]


@pytest.mark.parametrize("path", FACES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_face_calls_no_stage_function(path):
    bad = _violations(path)
    assert not bad, f"{path.relative_to(ROOT.parent)}: " + "; ".join(f"line {n}: {w}" for n, w in bad) + \
        " -- call organlab.engine instead"
