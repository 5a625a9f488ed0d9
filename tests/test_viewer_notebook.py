"""The viewer inside a notebook: a server started in a kernel, the page embedded."""

import os

import pytest

nbformat = pytest.importorskip("nbformat", reason="nbformat/nbclient not installed (notebook support is optional)")
nbclient = pytest.importorskip("nbclient", reason="nbformat/nbclient not installed (notebook support is optional)")

CELLS = [
    """import urllib.request
import numpy as np
from organlab.grid import VoxelGrid
from organlab.viewer import LiveView
grid = VoxelGrid.from_roi((-20, -20, 0), (20, 20, 40), 2.0)
x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
occ = x**2 + y**2 + (z - 20) ** 2 <= 15**2
live = LiveView(grid=None, roi=grid.bounds, port=0)
n = live.set_voxels(occ, grid)
live.iframe(height=400)""",
    """page = urllib.request.urlopen(live.url, timeout=30).read().decode()
print(n, "viser" in page.lower(), sorted(live.server.scene._handle_from_node_name)[:3])
live.stop()""",
]


@pytest.mark.slow
def test_live_view_in_a_notebook_kernel(tmp_path):
    nb = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell(c) for c in CELLS])
    env_path = os.environ.get("PYTHONPATH", "")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    os.environ["PYTHONPATH"] = root + (os.pathsep + env_path if env_path else "")
    try:
        nbclient.NotebookClient(nb, timeout=120, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    finally:
        os.environ["PYTHONPATH"] = env_path
    # (viser also prints its banner in the cell)
    html = [o["data"]["text/html"] for o in nb.cells[0].outputs if "<iframe" in o.get("data", {}).get("text/html", "")]
    assert len(html) == 1 and 'src="http://127.0.0.1:' in html[0]  # the page embedded in the cell
    out = [o["text"] for o in nb.cells[1].outputs if o.get("name") == "stdout" and o["text"][:1].isdigit()][0].split()
    from organlab.viewer._scene import surface_voxels
    import numpy as np
    from organlab.grid import VoxelGrid

    grid = VoxelGrid.from_roi((-20, -20, 0), (20, 20, 40), 2.0)
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    assert int(out[0]) == surface_voxels(x**2 + y**2 + (z - 20) ** 2 <= 15**2).sum()  # the kernel's scene
    assert out[1] == "True"  # the server in the kernel served the viewer's page
