"""The compiled topology checks of ``mesh_quality`` against the former pure numpy/scipy code, on meshes the code
was not written on: marching-cubes surfaces of random blobs (one or several pieces) made defective at random --
faces removed (holes), faces reversed (misoriented edges), faces repeated (non-manifold edges), vertices welded
across the surface (bow-ties), unreferenced vertices, vertices repeated.  Every figure must be the same
(integers: exactly), and so must the duplicate-vertex verdict of the repair's defect check.
"""

import numpy as np
import pytest

from organlab.grid import VoxelGrid
from organlab.mesh import Mesh
from organlab.surface import mesh_from_field
from organlab.surface._quality import (_mesh_quality, _mesh_quality_graph, _nonmanifold_vertices_graph,
                                       has_duplicate_vertices, nonmanifold_vertices)


def _blobs(seed):
    """Marching cubes of 1-3 random balls (a 24^3 grid, 1 mm): one piece or several, touching or not."""
    rng = np.random.default_rng(seed)
    grid = VoxelGrid(origin=(-12.0,) * 3, voxel_size=1.0, shape=(24, 24, 24))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    occ = np.zeros(grid.shape, bool)
    for _ in range(rng.integers(1, 4)):
        c, r = rng.uniform(-6, 6, 3), rng.uniform(3, 6)
        occ |= (x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 <= r * r
    return mesh_from_field(occ, grid), rng


def _damaged(seed):
    m, rng = _blobs(seed)
    v, f = m.vertices.copy(), m.faces.copy()
    kinds = rng.choice(["holes", "flip", "repeat", "weld", "unref", "dup", "none"], size=rng.integers(1, 4))
    for k in kinds:
        n = int(rng.integers(1, 6))
        if k == "holes":
            f = np.delete(f, rng.choice(len(f), n, replace=False), axis=0)
        elif k == "flip":
            i = rng.choice(len(f), n, replace=False)
            f[i] = f[i, ::-1]
        elif k == "repeat":
            f = np.concatenate([f, f[rng.choice(len(f), n)]])
        elif k == "weld":  # a vertex replaced by another one far away: bow-ties and non-manifold edges
            for a, b in rng.choice(len(v), (n, 2)):
                f[f == a] = b
        elif k == "unref":
            v = np.concatenate([v, rng.normal(size=(n, 3))])
        elif k == "dup":
            v = np.concatenate([v, v[rng.choice(len(v), n)]])
    return Mesh(v, f), kinds


@pytest.mark.parametrize("seed", range(40))
def test_compiled_topology_is_the_former_graph_one(seed):
    mesh, kinds = _damaged(seed)
    new, old = _mesh_quality(mesh), _mesh_quality_graph(Mesh(mesh.vertices, mesh.faces))
    assert new == old, kinds
    assert nonmanifold_vertices(mesh) == _nonmanifold_vertices_graph(mesh) == old["nonmanifold_vertices"]
    v = np.asarray(mesh.vertices)
    assert has_duplicate_vertices(mesh) == bool((np.diff(v[np.lexsort(v.T)], axis=0) == 0).all(axis=1).any())


def test_the_checks_can_tell():
    """The figures the damages must change (so the comparison above compares something): a clean ball has none."""
    m, _ = _blobs(3)
    q = _mesh_quality(m)
    assert q["boundary_edges"] == q["nonmanifold_edges"] == q["misoriented_edges"] == q["nonmanifold_vertices"] == 0
    f = m.faces.copy()
    f[0] = f[0, ::-1]  # one face reversed: its 3 edges run the same way as their neighbours'
    assert _mesh_quality(Mesh(m.vertices, f))["misoriented_edges"] == 3
    # two vertices of the surface welded: a bow-tie at the kept one (its two fans), found by both walks
    far = int(np.argmax(np.linalg.norm(m.vertices - m.vertices[0], axis=1)))
    g = np.where(m.faces == far, 0, m.faces)
    assert _mesh_quality(Mesh(m.vertices, g))["nonmanifold_vertices"] == 1
    assert _nonmanifold_vertices_graph(Mesh(m.vertices, g)) == 1
    assert not has_duplicate_vertices(m)
    assert has_duplicate_vertices(Mesh(np.concatenate([m.vertices, m.vertices[5:6] * -1.0 * -1.0]), m.faces))
    neg0 = np.array([[0.0, 1.0, 2.0], [-0.0, 1.0, 2.0], [np.inf, 0.0, 0.0], [np.inf, 0.0, 0.0]])
    assert has_duplicate_vertices(Mesh(neg0, np.zeros((0, 3), np.int64)))
    assert not has_duplicate_vertices(Mesh(neg0[2:], np.zeros((0, 3), np.int64)))  # inf - inf is not 0


def _drop_specks_graph(mesh, speck_mm):
    """The repair's speck removal as it was (scipy's graph components, ``np.minimum.at`` boxes)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces, dtype=np.int64)
    nv = len(v)
    n, lab = connected_components(coo_matrix((np.ones(2 * len(f)), (f[:, :2].ravel(), f[:, 1:].ravel())),
                                             shape=(nv, nv)), directed=False)
    lo, hi = np.full((n, 3), np.inf), np.full((n, 3), -np.inf)
    np.minimum.at(lo, lab, v)
    np.maximum.at(hi, lab, v)
    keep = (np.linalg.norm(hi - lo, axis=1) >= speck_mm)[lab[f[:, 0]]]
    if not keep.any():
        return None
    used = np.zeros(nv, dtype=bool)
    used[f[keep].ravel()] = True
    return Mesh(v[used], (np.cumsum(used) - 1)[f[keep]])


@pytest.mark.parametrize("seed", range(0, 40, 3))
def test_compiled_pieces_and_specks_are_the_former_ones(seed):
    from organlab.surface._repair import _drop_specks, _pieces

    mesh, _ = _damaged(seed)
    n, lab = _pieces(mesh.faces, len(mesh.vertices))
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f, nv = mesh.faces, len(mesh.vertices)
    old_n, old_lab = connected_components(coo_matrix((np.ones(2 * len(f)), (f[:, :2].ravel(), f[:, 1:].ravel())),
                                                     shape=(nv, nv)), directed=False)
    assert n == old_n and len(set(zip(lab.tolist(), old_lab.tolist()))) == n  # the same partition
    # diagonals of the pieces: a speck size below, between and above them (a ball of these is 6-24 mm across)
    for speck in (1.0, 9.0, 14.0, 40.0):
        new, old = _drop_specks(mesh, speck), _drop_specks_graph(mesh, speck)
        assert (new is None) == (old is None)
        if old is not None:
            assert np.array_equal(new.vertices, old.vertices) and np.array_equal(new.faces, old.faces)


def test_moved_meshes_figures_are_their_own():
    """A mesh with another's faces (``_moved``: smoothing, the volume restoration's offsets, one after another) takes
    the other's topology figures and computes its own geometry when asked: the figures of a fresh computation, also at
    the end of a chain of moves whose middle meshes were never asked about."""
    from organlab.surface._quality import _moved, mesh_quality

    grid = VoxelGrid(origin=(-8.0, -8.0, -8.0), voxel_size=1.0, shape=(17, 17, 17))
    x, y, z = np.meshgrid(*grid.axes(), indexing="ij")
    base = mesh_from_field(np.clip(6.3 - np.sqrt(x**2 + 1.7 * y**2 + z**2), 0.0, 1.0), grid)
    mesh_quality(base)
    rng = np.random.default_rng(2)
    chain = [base]
    for _ in range(3):  # each moved from the last, only the last asked
        chain.append(_moved(Mesh(chain[-1].vertices + rng.normal(scale=0.05, size=base.vertices.shape), base.faces),
                            chain[-1]))
    got = mesh_quality(chain[-1])
    want = _mesh_quality(Mesh(chain[-1].vertices.copy(), base.faces.copy()))
    assert got == want
    assert got["volume_mm3"] != mesh_quality(base)["volume_mm3"]  # its own geometry, not the base's
