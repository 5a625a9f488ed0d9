"""Issue 26, item 5: every reader of a user's file gives a valid result or a one-line OrganlabError.

Property-based (hypothesis, derandomized: the same examples every run): each reader is fed
malformed input derived from a valid file it reads (a value anywhere in the document replaced
by another type, a non-finite or huge number, deep nesting, a key removed; bytes truncated or
flipped).  Anything but a valid result or a one-line :class:`OrganlabError` (a traceback of any
other type, a message of several lines) fails.  Example counts are kept small (each example reads
a file); the size and time of each is bounded by the small session (320x240).
"""

import copy
import json
import shutil

import numpy as np
import pytest
from _hostile import small_calibrated

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from organlab import load_session  # noqa: E402
from organlab.calibration import Calibration  # noqa: E402
from organlab.errors import OrganlabError  # noqa: E402

FUZZ = settings(max_examples=int(__import__("os").environ.get("FUZZ_N", 200)), deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

_scalars = st.one_of(
    st.none(), st.booleans(), st.integers(-(10**30), 10**30), st.sampled_from([0, -1, 1, 2, 10**400 // 10**390]),
    st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([float("nan"), float("inf"), -1e308, 1e308, 1e-320]),
    st.text(max_size=12), st.sampled_from(["../../etc/passwd", "/etc/hostname", "\x1b[2J", "", "calibration.json"]),
)
_values = st.recursive(_scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                         st.dictionaries(st.text(max_size=6), inner, max_size=4)),
                       max_leaves=12)


def _paths(doc, prefix=()):
    """Every (path, value) inside a JSON document, the root included."""
    yield prefix, doc
    if len(prefix) > 8:  # not into a deep nest an earlier mutation made
        return
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc[:6]):  # a few items of a long list are enough
            yield from _paths(v, prefix + (i,))


def _deep(n):
    x = [1]
    for _ in range(n):
        x = [x]
    return x


@st.composite
def mutated(draw, doc):
    """``doc`` with one to three mutations: a value replaced, a key removed, a value nested deep."""
    doc = copy.deepcopy(doc)
    for _ in range(draw(st.integers(1, 3))):
        paths = [p for p, _ in _paths(doc) if p]
        if not paths:
            break
        path = draw(st.sampled_from(paths))
        parent = doc
        for k in path[:-1]:
            parent = parent[k]
        action = draw(st.sampled_from(["replace", "replace", "delete", "nest", "wrap"]))
        key = path[-1]
        if action == "delete" and isinstance(parent, dict):
            del parent[key]
        elif action == "nest":
            parent[key] = _deep(3000) if draw(st.booleans()) else [[[[parent[key]]]]]
        elif action == "wrap":
            parent[key] = {"value": parent[key]}
        else:
            parent[key] = draw(_values)
    return doc


def _dump(doc):
    try:
        return json.dumps(doc, allow_nan=True)  # NaN / Infinity as Python writes them: not JSON, refused
    except (RecursionError, ValueError):  # nested too deep for json.dumps itself: a deep file all the same
        return '{"views": ' + "[" * 100000 + "]" * 100000 + "}"


def npz_cases(good, raw):
    """Damaged ``.npz`` files: one array of ``good`` dropped or replaced, or the bytes ``raw`` corrupted."""
    return st.one_of(
        st.tuples(st.just("arrays"), st.sampled_from(sorted(good)), st.one_of(st.none(), _arrays)),
        st.tuples(st.just("bytes"), corrupted(raw), st.none()),
    )


def write_npz_case(path, good, case):
    """Write one case of :func:`npz_cases` to ``path``."""
    kind, a, b = case
    if kind == "bytes":
        path.write_bytes(a)
        return
    arrays = dict(good)
    if b is None:
        del arrays[a]
    else:
        arrays[a] = b
    np.savez(path, **arrays)


def _accept(fn):
    """A valid result or a one-line OrganlabError; anything else propagates (the test fails)."""
    try:
        return fn()
    except OrganlabError as e:
        assert "\n" not in str(e) and str(e).strip(), repr(str(e))
        return None


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return small_calibrated(tmp_path_factory)


@pytest.fixture(scope="module")
def scratch(small, tmp_path_factory):
    """A copy of the small session whose session.json / calibration.json each example rewrites."""
    root = tmp_path_factory.mktemp("fuzz") / "s"
    shutil.copytree(small, root, ignore=shutil.ignore_patterns("calibration_check"))
    return root


@pytest.mark.slow
def test_session_json_reader(small, scratch):
    doc = json.loads((small / "session.json").read_text())

    @FUZZ
    @given(mutated(doc))
    def check(bad):
        (scratch / "session.json").write_text(_dump(bad))
        s = _accept(lambda: load_session(scratch, check_images=False))
        if s is not None:  # valid: its paths stay in the folder, its numbers are finite, its name printable
            for v in s.views:
                assert v.image.resolve().is_relative_to(scratch.resolve())
            assert np.all(np.isfinite(s.roi_min)) and np.all(np.isfinite(s.roi_max))
            assert s.name.isprintable()

    check()


@pytest.mark.slow
def test_calibration_json_reader(small, scratch):
    doc = json.loads((small / "calibration.json").read_text())
    session = load_session(small)
    folder = scratch / "cal"
    folder.mkdir(exist_ok=True)

    @FUZZ
    @given(mutated(doc))
    def check(bad):
        (folder / "calibration.json").write_text(_dump(bad))
        cal = _accept(lambda: Calibration.load(folder, image_size=session.image_size))
        if cal is not None:  # what a run does with it next: verify, and the views' cameras
            _accept(lambda: cal.verify(session))
            _accept(lambda: cal.cameras(session))
            _accept(lambda: cal.mismatch(session))
            _accept(lambda: (cal.summary(), cal.warnings()))

    check()


# ------------------------------------------------------------- cases the trial found, each pinned
def test_paths_out_of_the_session_are_refused_with_one_line(small, tmp_path):
    root = tmp_path / "s"
    shutil.copytree(small, root, ignore=shutil.ignore_patterns("calibration_check"))
    doc = json.loads((root / "session.json").read_text())
    outside = tmp_path / "secret.png"
    shutil.copy(root / doc["views"][0]["image"], outside)
    (root / "views" / "link.png").symlink_to(outside)
    for path in ("../secret.png", str(outside), "views/link.png"):
        bad = copy.deepcopy(doc)
        bad["views"][1]["image"] = path
        (root / "session.json").write_text(json.dumps(bad))
        with pytest.raises(OrganlabError, match=r"views\[1\]\.image: .* is outside the session folder") as e:
            load_session(root)
        assert "\n" not in str(e.value)
        assert load_session(root, allow_outside_paths=True).views[1].image.resolve() == outside.resolve()


def test_session_name_with_terminal_escapes_is_printed_escaped(small, tmp_path):
    root = tmp_path / "s"
    shutil.copytree(small, root, ignore=shutil.ignore_patterns("calibration_check"))
    doc = json.loads((root / "session.json").read_text())
    doc["name"] = "ok\x1b[2J\x1b[1;1Horganlab reconstruct: fake -> /x\n  mesh volume  165.66 cm3"
    (root / "session.json").write_text(json.dumps(doc))
    name = load_session(root).name
    assert "\x1b" not in name and "\n" not in name and name.isprintable()
    assert name.startswith("ok\\x1b[2J") and "\\n" in name


@pytest.mark.parametrize("edit, needle", [
    (lambda d: d["reference"].__setitem__("volume_mm3", "__INF__"), "reference.volume_mm3"),
    (lambda d: d["roi"].__setitem__("max", [1e308, 70, 200]), "roi"),
    (lambda d: d["pattern"].__setitem__("square_size", "__INF__"), "pattern.square_size"),
    (lambda d: d.__setitem__("image_size", [10**12, 240]), "image_size"),
    (lambda d: d.__setitem__("name", ["a"]), "name"),
])
def test_bad_numbers_in_session_json_are_one_line(small, tmp_path, edit, needle):
    root = tmp_path / "s"
    shutil.copytree(small, root, ignore=shutil.ignore_patterns("calibration_check"))
    doc = json.loads((root / "session.json").read_text())
    edit(doc)
    (root / "session.json").write_text(json.dumps(doc).replace('"__INF__"', "1e400"))  # 1e400 parses as inf
    with pytest.raises(OrganlabError, match=needle.replace(".", r"\.").replace("[", r"\[")) as e:
        load_session(root, check_images=False)
    assert "\n" not in str(e.value)


def test_report_json_is_strict_json_even_with_a_non_finite_number(tmp_path):
    from organlab.session import write_json

    write_json(tmp_path / "r.json", {"a": float("nan"), "b": [np.float64("inf"), 1.5], "c": np.array([np.nan, 2.0])})
    text = (tmp_path / "r.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text, parse_constant=lambda c: pytest.fail(c)) == {"a": None, "b": [None, 1.5], "c": [None, 2.0]}


# ------------------------------------------------------------- binary readers: voxels.npz, meshes, camera files
@st.composite
def corrupted(draw, data):
    """``data`` truncated, with bytes flipped, or with a slice repeated (bytes)."""
    data = bytearray(data)
    kind = draw(st.sampled_from(["truncate", "flip", "flip", "repeat"]))
    if kind == "truncate":
        return bytes(data[: draw(st.integers(0, len(data)))])
    if kind == "repeat":
        a = draw(st.integers(0, len(data)))
        return bytes(data[:a] + data[a: a + 64] * draw(st.integers(2, 50)) + data[a:])
    for _ in range(draw(st.integers(1, 8))):
        i = draw(st.integers(0, max(0, len(data) - 1)))
        if data:
            data[i] = draw(st.integers(0, 255))
    return bytes(data)


_arrays = st.one_of(
    st.sampled_from([np.zeros(0), np.zeros((2, 2)), np.full(3, np.nan), np.array(np.inf), np.array(-1.0), np.array(0.0),
                     np.array([1e308, 0, 0]), np.array(["a", "b"]), np.zeros((1, 1, 1, 1), bool), np.array(3),
                     np.ones((3, 0, 2), bool), np.zeros((4, 4, 4), np.float32)]),
    st.integers(-3, 3).map(lambda k: np.array(k)),
)


@pytest.fixture(scope="module")
def result_dir(tmp_path_factory):
    """A small reconstruction's voxels.npz and mesh.ply (a 2 mm ball carved from a field, no session)."""
    from organlab.grid import VoxelGrid
    from organlab.surface import mesh_from_volume, write_ply

    folder = tmp_path_factory.mktemp("result")
    grid = VoxelGrid((-10.0, -10.0, -10.0), 2.0, (10, 10, 10))
    c = (np.indices(grid.shape).T + 0.5).T * 2.0 - 10.0
    field = np.clip(8.0 - np.sqrt((c ** 2).sum(0)), 0, 1).astype(np.float32)
    np.savez_compressed(folder / "voxels.npz", occupancy=field > 0.5, origin_mm=np.array(grid.origin, float),
                        voxel_size_mm=np.float64(2.0), field=field)
    write_ply(folder / "mesh.ply", mesh_from_volume(field, grid, level=0.5))
    return folder


@pytest.mark.slow
def test_voxels_npz_reader(result_dir, tmp_path_factory):
    from organlab.surface import load_voxels

    good = dict(np.load(result_dir / "voxels.npz"))
    raw = (result_dir / "voxels.npz").read_bytes()
    folder = tmp_path_factory.mktemp("vox")

    @FUZZ
    @given(npz_cases(good, raw))
    def check(case):
        write_npz_case(folder / "voxels.npz", good, case)
        out = _accept(lambda: load_voxels(folder))
        if out is not None:
            vol, grid = out
            assert vol.ndim == 3 and vol.shape == tuple(grid.shape) and np.all(np.isfinite(vol))
            assert np.isfinite(grid.voxel_size) and grid.voxel_size > 0 and np.all(np.isfinite(grid.origin))

    check()


@pytest.mark.slow
def test_mesh_reader(result_dir, tmp_path_factory):
    from organlab.surface import read_ply

    raw = (result_dir / "mesh.ply").read_bytes()
    path = tmp_path_factory.mktemp("ply") / "mesh.ply"

    @FUZZ
    @given(st.one_of(corrupted(raw), st.sampled_from([
        raw.replace(b"element vertex", b"element vertex 99999999999 "),
        raw.replace(b"element face", b"element face -5 "), b"ply\nend_header\n", b"", b"\xff" * 100])))
    def check(data):
        path.write_bytes(data)
        mesh = _accept(lambda: read_ply(path))
        if mesh is not None:
            v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
            assert v.ndim == 2 and v.shape[1] == 3 and f.ndim == 2 and f.shape[1] == 3
            assert f.size == 0 or (f.min() >= 0 and f.max() < len(v))

    check()


@pytest.mark.slow
def test_camera_file_readers(tmp_path_factory):
    from organlab.calibration import read_camera, write_bouguet, write_opencv
    from organlab.camera import Camera

    folder = tmp_path_factory.mktemp("camfiles")
    cam = Camera([[400.0, 0, 160], [0, 401, 120], [0, 0, 1]], [-0.2, 0.05, 0.001, 0, 0], image_size=(320, 240))
    files = {".m": write_bouguet(folder / "Calib_Results.m", cam).read_bytes(),
             ".yml": write_opencv(folder / "cam.yml", cam).read_bytes(),
             ".xml": write_opencv(folder / "cam.xml", cam).read_bytes(),
             ".json": json.dumps({"camera": {"K": cam.K.tolist(), "dist": cam.dist.tolist(), "image_size": [320, 240]}}).encode()}

    @FUZZ
    @given(st.sampled_from(sorted(files)).flatmap(lambda ext: st.tuples(st.just(ext), st.one_of(
        corrupted(files[ext]),
        st.sampled_from([b"fc = [ NaN ; 400 ];\ncc = [ 1 ; 2 ];\nnx = 320;\nny = 240;\n",
                         b"fc = [ 1e999 ; 400 ];\ncc = [ 1 ; 2 ];\nnx = -3;\nny = 240;\n",
                         b"%YAML:1.0\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ .nan, 0, 1, 0, 1, 1, 0, 0, 1 ]\n",
                         b"\x00" * 50])))))
    def check(case):
        ext, data = case
        path = folder / f"fuzz{ext}"
        path.write_bytes(data)
        c = _accept(lambda: read_camera(path, image_size=(320, 240)))
        if c is not None:
            assert np.all(np.isfinite(c.K)) and np.all(np.isfinite(c.dist)) and min(c.image_size) > 0

    check()


def test_cli_refuses_outside_paths_unless_allowed(small, tmp_path, capsys):
    from organlab.cli import main

    root = tmp_path / "s"
    shutil.copytree(small, root, ignore=shutil.ignore_patterns("calibration_check"))
    doc = json.loads((root / "session.json").read_text())
    shutil.copy(root / doc["views"][0]["image"], tmp_path / "outside.png")
    doc["views"][0]["image"] = "../outside.png"
    (root / "session.json").write_text(json.dumps(doc))
    assert main(["reconstruct", str(root), "--out", str(tmp_path / "o"), "--quiet", "--voxel-size", "8"]) == 2
    err = capsys.readouterr().err
    assert "outside the session folder" in err and len(err.strip().splitlines()) == 1
