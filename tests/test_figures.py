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
