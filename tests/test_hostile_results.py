"""Issue 26 (corrupt results) and issue 19 (results read through their type).

`organlab mesh` and `organlab view --result` read a result folder through
:meth:`organlab.engine.Reconstruction.load`, which reads every file through organlab.validate:
report.json strict and typed, voxels.npz never with pickles and its decompressed size checked
before decoding, mesh.ply checked.  A damaged file of any kind is one line, exit 2, no traceback;
the fuzz below (hypothesis, derandomized) feeds the reader malformed versions of a real result's
files and accepts only a valid result or a one-line OrganlabError.
"""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _hostile import small_calibrated

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from test_hostile_fuzz import _accept, _dump, corrupted, mutated, npz_cases, write_npz_case  # noqa: E402

from organlab import load_session  # noqa: E402
from organlab.cli import main  # noqa: E402
from organlab.engine import Reconstruction, Settings, run  # noqa: E402
from organlab.errors import OrganlabError  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
# each example reads a whole result folder (a 4 mm model: ~0.05 s); 60 per reader keeps each test under ~10 s
FUZZ = settings(max_examples=int(os.environ.get("FUZZ_N", 60)), deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    """The small session (12 views, 320x240, seed 7) reconstructed at 4 mm and saved: (session, folder, rec)."""
    session = small_calibrated(tmp_path_factory)
    folder = tmp_path_factory.mktemp("result") / "out"
    rec = run(session, Settings(voxel_size=4.0, finish=False))
    rec.save(folder)
    return session, folder, rec


def _copy(folder, dest):
    shutil.rmtree(dest, ignore_errors=True)
    shutil.copytree(folder, dest)
    return dest


def _valid(rec):
    """What a result read back must satisfy."""
    assert rec.occupancy.dtype == bool and rec.occupancy.shape == tuple(rec.grid.shape)
    assert np.isfinite(rec.grid.voxel_size) and rec.grid.voxel_size > 0 and np.all(np.isfinite(rec.grid.origin))
    v, f = np.asarray(rec.mesh.vertices), np.asarray(rec.mesh.faces)
    assert np.all(np.isfinite(v)) and (f.size == 0 or (f.min() >= 0 and f.max() < len(v)))
    vol = rec.surface_volume()
    assert vol.shape == rec.occupancy.shape and np.all(np.isfinite(vol))
    assert isinstance(rec.report, dict)
    if rec.agreement is not None:
        n = len(rec.agreement.names)
        assert len(rec.agreement.iou) == n and sorted(rec.agreement.ranking) == list(range(n))
        rec.agreement.line()  # the summary line the CLI and the viewer print
    rec.settings.validate()


def test_a_saved_result_reads_back_equal(result):
    _, folder, rec = result
    back = Reconstruction.load(folder)
    _valid(back)
    assert np.array_equal(back.occupancy, rec.occupancy) and back.grid == rec.grid
    assert np.array_equal(back.surface_volume(), np.asarray(rec.field, dtype=np.float32))
    assert back.report == json.loads((folder / "report.json").read_text())
    assert back.agreement.ranking == rec.agreement.ranking  # the same worst view as the run
    assert back.mesh.volume == pytest.approx(rec.mesh.volume, rel=1e-5)  # float32 vertices in PLY


@pytest.mark.slow
def test_report_json_fuzz(result, tmp_path):
    from organlab.viewer._app import check_result_folder

    session_dir, folder, _ = result
    session = load_session(session_dir)
    work = _copy(folder, tmp_path / "r")
    doc = json.loads((folder / "report.json").read_text())

    @FUZZ
    @given(mutated(doc))
    def check(bad):
        (work / "report.json").write_text(_dump(bad))
        rec = _accept(lambda: Reconstruction.load(work))
        if rec is not None:
            _valid(rec)
        _accept(lambda: check_result_folder(work, session))  # the viewer's --result check, before its server

    check()


@pytest.mark.slow
def test_voxels_npz_fuzz(result, tmp_path):
    _, folder, _ = result
    work = _copy(folder, tmp_path / "r")
    good = dict(np.load(folder / "voxels.npz"))
    raw = (folder / "voxels.npz").read_bytes()

    @FUZZ
    @given(npz_cases(good, raw))
    def check(case):
        write_npz_case(work / "voxels.npz", good, case)
        rec = _accept(lambda: Reconstruction.load(work))
        if rec is not None:
            _valid(rec)

    check()


@pytest.mark.slow
def test_mesh_ply_fuzz(result, tmp_path):
    _, folder, _ = result
    work = _copy(folder, tmp_path / "r")
    raw = (folder / "mesh.ply").read_bytes()

    @FUZZ
    @given(corrupted(raw))
    def check(data):
        (work / "mesh.ply").write_bytes(data)
        rec = _accept(lambda: Reconstruction.load(work))
        if rec is not None:
            _valid(rec)

    check()


class _Boom:
    """Unpickling this would create a file: proof that a pickle ran."""

    def __init__(self, path):
        self.path = path

    def __reduce__(self):
        return (Path.touch, (Path(self.path),))


def test_a_pickle_in_voxels_npz_is_refused_unrun(result, tmp_path):
    _, folder, _ = result
    work = _copy(folder, tmp_path / "r")
    arrays = dict(np.load(folder / "voxels.npz"))
    arrays["colors"] = np.array([_Boom(tmp_path / "pwned")], dtype=object)
    np.savez(work / "voxels.npz", **arrays)  # numpy pickles object arrays
    with pytest.raises(OrganlabError, match="colors: dtype object, not plain numbers"):
        Reconstruction.load(work)
    assert not (tmp_path / "pwned").exists()


def test_a_small_file_holding_a_huge_array_is_refused_before_decoding(result, tmp_path, monkeypatch):
    import time

    import organlab.engine as engine

    _, folder, _ = result
    work = _copy(folder, tmp_path / "r")
    np.savez_compressed(work / "voxels.npz", occupancy=np.zeros((500, 500, 400), bool), origin_mm=np.zeros(3),
                        voxel_size_mm=np.float64(1.0))
    assert (work / "voxels.npz").stat().st_size < 1 << 20  # 100 MB of booleans in under 1 MB
    monkeypatch.setattr(engine, "available_memory", lambda: 64 << 20)  # as if 64 MiB were free
    t0 = time.process_time()
    with pytest.raises(OrganlabError, match=r"voxels.npz: its arrays take 95 MiB decompressed, more than the 64 MiB"):
        Reconstruction.load(work)
    assert time.process_time() - t0 < 1.0  # refused from the zip's directory, nothing decompressed


@pytest.mark.parametrize("damage, needle", [
    (lambda d: (d / "report.json").write_text('{"views": [' * 5000), "nested"),
    (lambda d: (d / "report.json").write_text('{"method": NaN}'), "not JSON"),
    (lambda d: (d / "report.json").write_text('{"method": "magic"}'), "method: must be one of"),
    (lambda d: (d / "report.json").write_text('{"views": [{"image": "a", "agreement": {"iou": "x"}}]}'), "iou"),
    (lambda d: (d / "voxels.npz").write_bytes(b"PK\x03\x04" + b"\0" * 40), "voxels.npz: unreadable"),
    (lambda d: (d / "voxels.npz").write_bytes((d / "voxels.npz").read_bytes()[:-100]), "voxels.npz"),
    (lambda d: np.savez(d / "voxels.npz", occupancy=np.ones((3, 3, 3), bool), origin_mm=np.zeros(3),
                        voxel_size_mm=np.float64(np.nan)), "voxel_size_mm: must be a finite number"),
])
def test_organlab_mesh_on_a_damaged_result_is_one_line(result, tmp_path, capsys, damage, needle):
    _, folder, _ = result
    work = _copy(folder, tmp_path / "r")
    damage(work)
    assert main(["mesh", str(work)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and needle in err and "Traceback" not in err, err
    assert not (work / "surface").exists()


@pytest.mark.parametrize("damage, needle", [
    (lambda d: (d / "mesh.ply").write_bytes((d / "mesh.ply").read_bytes()[:300]), "mesh.ply: not a mesh"),
    (lambda d: (d / "mesh.ply").unlink(), "mesh.ply: missing"),
])
def test_a_damaged_or_missing_mesh_is_one_line(result, tmp_path, damage, needle):
    _, folder, _ = result
    work = _copy(folder, tmp_path / "r")
    damage(work)
    with pytest.raises(OrganlabError, match=needle):
        Reconstruction.load(work)
    assert Reconstruction.load(work, mesh=False).mesh is None  # organlab mesh does not need it


def test_organlab_mesh_reads_through_the_result_type(result, tmp_path, capsys):
    """The mesh of `organlab mesh` is the surface of Reconstruction.load's volume (coloured voxels win over the field)."""
    _, folder, rec = result
    work = _copy(folder, tmp_path / "r")
    assert main(["mesh", str(work), "--repair"]) == 0
    surf = json.loads((work / "surface" / "surface_report.json").read_text())
    # repair only: the volume of the raw marching-cubes surface of the field, within the repair's change
    assert surf["final"]["volume_mm3"] == pytest.approx(rec.raw_mesh.volume, rel=0.02)


@pytest.mark.slow
def test_view_result_with_a_damaged_file_is_one_line_before_the_server(result, tmp_path):
    session, folder, _ = result
    work = _copy(folder, tmp_path / "r")
    (work / "voxels.npz").write_bytes(b"not a zip at all")
    p = subprocess.run([sys.executable, "-m", "organlab", "view", str(session), "--result", str(work), "--port", "0"],
                       capture_output=True, text=True, timeout=60, env=dict(os.environ, PYTHONPATH=str(ROOT)),
                       stdin=subprocess.DEVNULL)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode == 2 and len(lines) == 1 and "voxels.npz: unreadable" in lines[0], p.stderr
    assert "http://" not in p.stdout  # refused before the server started


# ------------------------------------------------------------- read-only folders and a full disk, on every command
def _immutable(folder, on=True):
    """chattr +i: a folder even root cannot write into (root ignores permission bits); False when unsupported."""
    return subprocess.run(["chattr", "+i" if on else "-i", str(folder)], capture_output=True).returncode == 0


@pytest.fixture
def read_only(tmp_path):
    made = []

    def make(folder):
        if not _immutable(folder):
            pytest.skip("chattr +i not permitted here: no folder is read-only for root")
        made.append(folder)
        return folder

    yield make
    for f in made:
        _immutable(f, on=False)


def _one_line_error(capsys, *needles):
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("organlab: error:") and "Traceback" not in err, err
    assert all(n in lines[0] for n in needles), lines[0]


def test_mesh_into_a_read_only_result_folder_is_one_line(result, tmp_path, capsys, read_only):
    _, folder, _ = result
    work = read_only(_copy(folder, tmp_path / "r"))
    assert main(["mesh", str(work), "--repair"]) == 2
    _one_line_error(capsys, str(work), "cannot write here")


def test_calibrate_into_a_read_only_folder_is_refused_before_the_fit(result, tmp_path, capsys, read_only):
    import time

    session, _, _ = result
    out = tmp_path / "cal"
    out.mkdir()
    read_only(out)
    t0 = time.process_time()
    assert main(["calibrate", str(session), "--out", str(out), "--quiet"]) == 2
    assert time.process_time() - t0 < 2.0  # before the fit (~10 s of CPU), not after it
    _one_line_error(capsys, "cannot write here")


def test_reconstruct_into_a_read_only_parent_is_one_line_before_the_work(result, tmp_path, capsys, read_only):
    session, _, _ = result
    parent = tmp_path / "p"
    parent.mkdir()
    read_only(parent)
    assert main(["reconstruct", str(session), "--out", str(parent / "out"), "--voxel-size", "4", "--quiet"]) == 2
    _one_line_error(capsys, str(parent))


@pytest.mark.parametrize("command", ["mesh", "calibrate"])
def test_a_full_disk_on_any_command_is_one_line(result, tmp_path, capsys, monkeypatch, command):
    """ENOSPC raised where the files are written (no real full disk here): one line naming the file, exit 2."""
    import errno

    import organlab.cli as cli
    import organlab.surface._result as sr

    session, folder, _ = result

    def full(path, *a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    if command == "mesh":
        work = _copy(folder, tmp_path / "r")
        monkeypatch.setattr(sr, "write_stl", full)
        argv = ["mesh", str(work), "--repair"]
    else:
        monkeypatch.setattr(cli, "check_figures", lambda s, c, out: full(Path(out) / "intrinsic_000.png"))
        argv = ["calibrate", str(session), "--out", str(tmp_path / "cal"), "--quiet"]
    assert main(argv) == 2
    _one_line_error(capsys, "No space left on device", str(tmp_path))
    if command == "calibrate":
        assert not (tmp_path / "cal" / "calibration.json").exists()  # never a calibration.json without its figures


def test_mesh_with_a_tiny_remesh_edge_is_refused_before_remeshing(result, tmp_path, capsys):
    """--remesh 0.001 on a 4 mm model: about 1e11 faces; pymeshlab would try (measured: 1.25 KB per face)."""
    import time

    _, folder, rec = result
    work = _copy(folder, tmp_path / "r")
    t0 = time.process_time()
    assert main(["mesh", str(work), "--remesh", "0.001"]) == 2
    assert time.process_time() - t0 < 5.0
    _one_line_error(capsys, "--remesh 0.001", "million faces", "give --remesh")
    from organlab.preflight import check_remesh_memory

    # the bound itself: the measured ball (4890 mm^2 at 0.25 mm: 172 722 faces, 206 MB) fits in 1 GiB, not in 100 MB
    assert check_remesh_memory(4890.0, 0.25, max_memory=1 << 30) == pytest.approx(180_702 * 1300, rel=0.01)
    with pytest.raises(OrganlabError, match="give --remesh 0.3"):
        check_remesh_memory(4890.0, 0.25, max_memory=150 << 20)


@pytest.mark.parametrize("text, needle", [
    ('{"camera": ' + "[" * 5000 + "]" * 5000 + "}", "nested 5001 deep"),  # was a RecursionError traceback
    ('{"camera": {"K": [[NaN, 0, 1], [0, 1, 1], [0, 0, 1]]}}', "not JSON"),
    ('["camera"]', "has no usable cameras"),
])
def test_export_cameras_from_a_damaged_report_is_one_line(tmp_path, capsys, text, needle):
    (tmp_path / "report.json").write_text(text)
    assert main(["export-cameras", str(tmp_path), "--format", "colmap"]) == 2
    _one_line_error(capsys, "report.json", needle)
