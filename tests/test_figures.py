import cv2
import numpy as np

from organlab.figures import mesh_snapshot
from organlab.grid import VoxelGrid
from organlab.surface import mesh_from_volume


def test_mesh_snapshot_draws_the_mesh(tmp_path):
    grid = VoxelGrid.from_roi([-30, -30, 0], [30, 30, 60], 2.0)
    c = grid.centers().reshape(*grid.shape, 3)
    occ = np.linalg.norm(c - [0, 0, 30], axis=-1) < 20
    mesh = mesh_from_volume(occ, grid)
    path = mesh_snapshot(mesh, tmp_path / "m.png", window_size=(320, 240), title="sphere")
    img = cv2.imread(str(path))
    assert img.shape == (240, 320, 3)
    # the mesh is drawn in its colour (reddish: R clearly above B) over a white background
    reddish = (img[:, :, 2].astype(int) - img[:, :, 0]) > 30
    assert 0.03 < reddish.mean() < 0.6
    ys, xs = np.nonzero(reddish)
    assert abs(xs.mean() - 160) < 40 and abs(ys.mean() - 120) < 50


def test_mesh_snapshot_keeps_its_title_and_axis_labels_inside(tmp_path):
    """The demo's mesh.png: nothing drawn within 4 px of an edge (with a 1.15 margin the x axis title was cut at the
    bottom: 18 dark px in the last 4 rows of the demo's picture), and the title on a line of its own."""
    grid = VoxelGrid.from_roi([-30, -30, 0], [30, 30, 180], 3.0)
    c = grid.centers().reshape(*grid.shape, 3)
    # a tall spindle like the phantom (the demo's picture: an aorta 180 mm tall, 60 mm wide)
    r = 10 + 20 * np.sin(np.pi * np.clip(c[..., 2] / 180, 0, 1))
    occ = np.hypot(c[..., 0], c[..., 1]) < r
    mesh = mesh_from_volume(occ, grid)
    path = mesh_snapshot(mesh, tmp_path / "m.png", title="aaa_phantom: 165.2 cm3 at 1 mm (-0.29 % vs reference)")
    img = cv2.imread(str(path))
    assert img.shape == (600, 800, 3)
    ink = (img < 200).any(axis=2)
    assert not ink[:4].any() and not ink[-4:].any() and not ink[:, :4].any() and not ink[:, -4:].any()
    rows = np.nonzero(ink.any(axis=1))[0]
    title = rows[rows < 40]
    assert len(title) > 8  # the title's line of text
    below = rows[rows > title.max()]
    assert below.min() - title.max() > 10, (title.max(), below.min())  # a blank band between title and scene
