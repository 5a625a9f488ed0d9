"""The bundled sample session, as `make demo` runs it: calibration from its own
images, then the reconstruction, against the phantom's exact volume."""

import json
import shutil

import numpy as np
import pytest

from organlab import load_session
from organlab.pipeline import reconstruct, write_outputs
from organlab.synthetic import with_true_cameras
from tests._shared_data import SAMPLE

SPEC_REPORT_KEYS = {"volume_mm3", "mesh_volume_mm3", "mesh_area_mm2", "watertight", "voxel_size_mm", "timings_s", "views", "camera"}

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    """Copies of the sample: as shipped (calibrates itself), and with the true cameras given."""
    tmp = tmp_path_factory.mktemp("sample")
    ignore = shutil.ignore_patterns("calibration.json", "calibration_check")
    calibrated = tmp / "calibrated"
    shutil.copytree(SAMPLE, calibrated, ignore=ignore)
    true = with_true_cameras(SAMPLE, tmp / "true")
    truth = json.loads((true / "truth.json").read_text())
    return calibrated, true, truth


@pytest.fixture(scope="module")
def demo(sessions):
    return reconstruct(sessions[0], voxel_size=1.0)


def test_demo_report_matches_the_spec(demo, sessions, tmp_path):
    paths = write_outputs(demo, tmp_path)
    report = json.loads(paths["report"].read_text())
    assert SPEC_REPORT_KEYS <= report.keys()
    assert set(report["timings_s"]) == {"calibration", "silhouettes", "carving", "surface"}
    assert {"K", "dist", "rms_px"} <= report["camera"].keys() and report["camera"]["rms_px"] < 0.2
    assert len(report["views"]) == 36 and report["watertight"] is True
    assert report["calibration"]["source"] == "computed"
    # the calibration goes to the output folder, never into the session
    assert paths["calibration"] == tmp_path / "calibration.json" and paths["calibration"].is_file()
    assert not (sessions[0] / "calibration.json").exists()


def test_volume_within_half_a_percent_at_1mm(demo, sessions):
    true_volume = sessions[2]["volume_mm3"]
    assert demo.report["reference"]["volume_mm3"] == true_volume
    assert abs(demo.mesh.volume / true_volume - 1) < 0.005
    assert demo.mesh.is_watertight


def test_volume_within_one_percent_at_2mm(demo, sessions):
    rec = reconstruct(load_session(sessions[0]), voxel_size=2.0, calibration=demo.calibration)
    assert "calibration" not in rec.report["timings_s"] and rec.report["calibration"]["source"] == "given, verified"
    assert abs(rec.mesh.volume / sessions[2]["volume_mm3"] - 1) < 0.01


def test_calibrated_cameras_reconstruct_like_the_true_ones(demo, sessions):
    truth = sessions[2]
    for cam, tv in zip(demo.cameras, truth["views"]):
        true_centre = -np.asarray(tv["R"]).T @ np.asarray(tv["t"])
        assert np.linalg.norm(cam.center - true_centre) < 1.0
    with_true = reconstruct(sessions[1], voxel_size=1.0)
    assert "calibration" not in with_true.report["timings_s"]
    assert abs(demo.mesh.volume / with_true.mesh.volume - 1) < 0.005
