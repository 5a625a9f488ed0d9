"""The narrow-band hull field and its surface against the field computed at every voxel.

``hull_field`` decides blocks of voxels coarse to fine and computes the field
only in the blocks the surface crosses; ``_dense_field`` computes it at every
voxel (the method before the band, kept as the yardstick).  The band must give
the same values (0 differences), and its chunked marching cubes the same mesh
as ``mesh_from_volume`` of the dense field up to float32 rounding.

Scenes: the bundled sample session (the scene the defaults were tuned on), and
a scene nothing was tuned on: an off-axis sphere and a cylinder seen by
cameras at scattered azimuths and elevations (not a turntable ring), rolled
about their optical axes, with pincushion and tangential distortion, skew, a
non-4:3 image, and one camera so close that the grid leaves its image.
"""

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from organlab.camera import Camera
from organlab.carving import BandField, hull_field
from organlab.carving._field import _as_coverage, _dense_field
from organlab.grid import VoxelGrid
from organlab.surface import mesh_from_field, mesh_from_volume
from organlab.synthetic import Cylinder, Sphere, render_masks
from tests._shared_data import SAMPLE


def _look_at(centre, target, roll_deg):
    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    c, s = np.cos(np.deg2rad(roll_deg)), np.sin(np.deg2rad(roll_deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R


def _odd_cameras():
    """14 cameras no default saw: scattered, rolled, pincushion + tangential distortion, skew, 360 x 300 px."""
    rng = np.random.default_rng(7)
    K = np.array([[420.0, 1.5, 171.0], [0.0, 431.0, 158.0], [0.0, 0.0, 1.0]])
    dist = [0.12, -0.05, 0.004, -0.003, 0.0]
    cams = []
    for i in range(14):
        az = np.deg2rad(360.0 * i / 14 + rng.uniform(-10, 10))
        el = np.deg2rad(rng.uniform(-15, 60))
        d = 180.0 if i else 95.0  # the first is close: the grid reaches beyond its image
        centre = np.array([d * np.cos(el) * np.cos(az), d * np.cos(el) * np.sin(az), 30.0 + d * np.sin(el)])
        R = _look_at(centre, [4.0, -3.0, 30.0], rng.uniform(-40, 40))
        cams.append(Camera(K, dist, R, -R @ centre, (360, 300)))
    return cams


def _compare(coverages, cameras, grid, **kw):
    """Band vs dense field and meshes; returns (band, largest vertex difference mm, relative volume difference)."""
    band = hull_field(coverages, cameras, grid, sparse=True, **kw)
    assert isinstance(band, BandField)
    covs = [_as_coverage(c, cam, i) for i, (c, cam) in enumerate(zip(coverages, cameras))]
    dense = _dense_field(covs, cameras, grid, **kw)
    assert np.array_equal(band.dense(), dense)  # the same values, voxel for voxel
    assert np.array_equal(np.asarray(band), dense) and band.shape == dense.shape
    assert np.array_equal(band.occupancy(), dense >= 0.5)
    assert band.n_inside() == int((dense >= 0.5).sum())
    assert np.array_equal(hull_field(coverages, cameras, grid, **kw), dense)  # the dense return still works
    m, md = mesh_from_field(band, grid), mesh_from_volume(dense, grid)
    assert m.is_watertight and m.volume > 0
    assert abs(len(m.faces) - len(md.faces)) <= 1e-4 * len(md.faces)
    # both ways: every vertex of one mesh has a twin in the other
    dv = max(cKDTree(md.vertices).query(m.vertices)[0].max(), cKDTree(m.vertices).query(md.vertices)[0].max())
    return band, dv, m.volume / md.volume - 1


@pytest.fixture(scope="module")
def sample():
    from organlab import load_session
    from organlab.pipeline import session_cameras
    from organlab.silhouette import session_silhouettes
    from organlab.synthetic import with_true_cameras

    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        session = load_session(with_true_cameras(SAMPLE, Path(tmp) / "true"))
        cams = session_cameras(session)
        cov = [s.coverage for s in session_silhouettes(session)]
    return session, cams, cov


@pytest.mark.slow
@pytest.mark.parametrize("voxel", [1.0, 0.5])
def test_band_field_equals_the_dense_field_on_the_sample(sample, voxel):
    session, cams, cov = sample
    grid = VoxelGrid.from_roi(session.roi_min, session.roi_max, voxel)
    band, dv, dvol = _compare(cov, cams, grid)
    # measured: largest vertex difference 7.6e-6 mm at 1 and 0.5 mm (float32 rounding of ~100 mm
    # coordinates), volume difference 3e-10 (1 mm) and 2e-11 (0.5 mm) of the volume
    assert dv < 1e-4
    assert abs(dvol) < 1e-8
    # the band is what grows: at 0.5 mm it holds under 5 % of the grid's voxels (measured 2.3 %)
    assert band.n_band_voxels < 0.05 * grid.n_voxels


@pytest.mark.parametrize(
    "specimen, voxel, kw",
    [
        (Sphere((4.0, -3.0, 30.0), 21.0), 2.0, {}),
        (Sphere((4.0, -3.0, 30.0), 21.0), 1.5, {"tolerance": 1, "min_views": 3}),
        (Cylinder((3.0, -2.0), 15.0, 10.0, 52.0), 1.5, {}),
    ],
)
def test_band_field_equals_the_dense_field_on_a_scene_no_default_saw(specimen, voxel, kw):
    cams = _odd_cameras()
    cov = list(render_masks(specimen, cams, supersample=3))
    # the close camera sees only part of the grid: views that cannot see a voxel do not constrain it
    grid = VoxelGrid.from_roi([-30.0, -30.0, 0.0], [34.0, 30.0, 62.0], voxel)
    band, dv, dvol = _compare(cov, cams, grid, **kw)
    # measured: under 1e-5 mm and 1e-9 of the volume (float32 rounding only)
    assert dv < 1e-4
    assert abs(dvol) < 1e-8
    assert 0 < len(band.values) and band.n_band_voxels < 0.5 * grid.n_voxels
    # blocks were decided both ways without computing them
    assert (band.states == 0).any() and (band.states == 1).any()


def test_warm_kernels_load_what_the_hull_calls():
    """``carving.warm_kernels`` (the command calls it on its loading thread, beside the silhouettes: issue 24) must
    load every specialisation a real hull then calls, or the hull stage loads (and a fresh clone compiles) the
    others on the critical path.  In a new process: after it, a hull of six rendered views of a sphere (float32
    coverage, as the silhouettes give) adds no signature to the band's, the distance images' and the band field's
    kernels.  Measured: 7 kernels hold a signature, 0 new ones."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        import numpy as np
        from numba.core.dispatcher import Dispatcher
        import organlab.bandfield as bf
        from organlab.carving import _band, _field, hull_field, warm_kernels
        from organlab.grid import VoxelGrid
        from organlab.synthetic import Sphere, default_camera, render_masks

        def sigs():
            return {f"{m.__name__}.{k}": set(map(str, v.signatures)) for m in (_band, _field, bf)
                    for k, v in vars(m).items() if isinstance(v, Dispatcher)}

        warm_kernels()
        before = sigs()
        cams = [default_camera((160, 120)).at_table_angle(a) for a in range(0, 360, 60)]
        covs = [np.asarray(c, np.float32) for c in render_masks(Sphere(center=(0, 0, 40), radius=20), cams)]
        field = hull_field(covs, cams, VoxelGrid.from_roi((-40, -40, 0), (40, 40, 80), 2.0), sparse=True)
        assert field.n_inside() > 0 and field.occupancy().any()
        after = sigs()
        print("USED", sum(bool(s) for s in after.values()))
        print("NEW", sorted(f"{k} {s}" for k in after for s in after[k] - before[k]))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[1]).stdout
    used = int(out.split("USED")[1].split()[0])
    assert used >= 7, out  # _outline_distance, _signed, _classify, _paint, _band_values, _count_inside, _fill_occupancy
    assert out.split("NEW")[1].strip() == "[]", out
