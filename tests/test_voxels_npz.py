"""``voxels.npz`` stores the hull field as its band, and old files with a dense ``field`` still load.

``write_outputs`` stores a :class:`organlab.carving.BandField` as
``field_block``, ``field_states`` and ``field_values`` (the band blocks only);
``load_voxels`` (``organlab mesh``, the viewer's ``--result`` AAA measures)
gives back the dense field, value for value, from these arrays and from the
dense ``field`` earlier versions wrote.  Damaged arrays are refused with one
line naming the file, the array and the fix.

Scenes: the bundled sample at 2 mm (what users run), and a hand-made band
nothing was tuned on: a grid that is not a whole number of blocks, blocks of
3 voxels, band rows in a shuffled order (the carving's order is not the
file's).
"""

import json

import numpy as np
import pytest

from organlab.carving import BandField
from organlab.cli import main
from organlab.errors import OrganlabError
from organlab.grid import VoxelGrid
from organlab.pipeline import reconstruct, write_outputs
from organlab.surface import load_voxels, mesh_from_volume
from tests._shared_data import SAMPLE


@pytest.fixture(scope="module")
def rec():
    return reconstruct(SAMPLE, voxel_size=2.0)


@pytest.fixture(scope="module")
def folders(rec, tmp_path_factory):
    """The result folder as written now, and a copy whose voxels.npz is as earlier versions wrote it."""
    new = tmp_path_factory.mktemp("new")
    write_outputs(rec, new)
    old = tmp_path_factory.mktemp("old")
    for p in new.iterdir():
        if p.is_file() and p.name != "voxels.npz":
            (old / p.name).write_bytes(p.read_bytes())
    np.savez_compressed(old / "voxels.npz", occupancy=rec.occupancy, origin_mm=np.asarray(rec.grid.origin),
                        voxel_size_mm=np.float64(rec.grid.voxel_size), field=np.asarray(rec.field))
    return new, old


def _odd_band():
    """A band field no carving made: 13 x 10 x 7 voxels in blocks of 3 (partial blocks), rows shuffled."""
    rng = np.random.default_rng(3)
    grid = VoxelGrid((-4.0, 2.0, 0.5), 0.7, (13, 10, 7))
    states = rng.integers(0, 3, size=(5, 4, 3)).astype(np.int8)
    n = int((states == 2).sum())
    index = np.full(states.shape, -1, dtype=np.int32)
    index[states == 2] = rng.permutation(n).astype(np.int32)
    values = rng.uniform(-0.5, 1.5, size=(n, 3, 3, 3)).astype(np.float32)
    return BandField(grid, 3, states, index, values)


def _npz_round_trip(field, path):
    np.savez_compressed(path, **field.to_arrays())
    with np.load(path, allow_pickle=False) as z:
        return BandField.from_arrays(z, field.grid, source=path)


def test_band_round_trip_is_exact(rec, tmp_path):
    odd = _odd_band()
    assert not np.array_equal(odd.index[odd.states == 2], np.arange(len(odd.values)))  # rows out of file order
    for field in (rec.field, odd):
        back = _npz_round_trip(field, tmp_path / "f.npz")
        assert np.array_equal(back.dense(), np.asarray(field))  # value for value
        assert np.array_equal(back.occupancy(), field.occupancy())
        assert back.shape == field.shape and back.block == field.block
    # the file holds the band, not the volume: the sample at 2 mm has 607 band blocks of 64 voxels
    # in a 70 x 70 x 100 grid (measured; this checks nothing of grid size is stored besides occupancy)
    arrays = rec.field.to_arrays()
    assert arrays["field_values"].shape == (int((rec.field.states == 2).sum()), 4, 4, 4)
    assert arrays["field_values"].size < 0.1 * np.prod(rec.grid.shape)


def test_new_and_old_files_load_the_same_volume(rec, folders):
    new, old = folders
    with np.load(new / "voxels.npz", allow_pickle=False) as z:
        assert "field" not in z.files and {"field_block", "field_states", "field_values"} <= set(z.files)
        assert z["field_states"].dtype == np.int8 and z["field_values"].dtype == np.float32
    dense = np.asarray(rec.field)
    for folder in (new, old):
        vol, grid = load_voxels(folder)
        assert vol.dtype == np.float32 and np.array_equal(vol, dense)
        assert grid.shape == rec.grid.shape and grid.voxel_size == 2.0
        np.testing.assert_array_equal(grid.origin, rec.grid.origin)
    # the surface of the loaded field is the pipeline's raw surface
    assert mesh_from_volume(load_voxels(new)[0], rec.grid, level=0.5).volume == pytest.approx(rec.raw_mesh.volume,
                                                                                              rel=1e-9)


def test_a_dense_field_in_memory_is_written_as_before(rec, tmp_path):
    """A Reconstruction holding a dense field (hull_field(sparse=False)) is written as the dense 'field'."""
    from dataclasses import replace

    write_outputs(replace(rec, field=np.asarray(rec.field)), tmp_path)
    with np.load(tmp_path / "voxels.npz", allow_pickle=False) as z:
        assert "field_states" not in z.files
    assert np.array_equal(load_voxels(tmp_path)[0], np.asarray(rec.field))


def test_mesh_command_on_new_and_old_files(rec, folders, capsys):
    new, old = folders
    volumes = []
    for folder in (new, old):
        assert main(["mesh", str(folder), "--repair", "--remesh", "4"]) == 0
        report = json.loads((folder / "surface" / "surface_report.json").read_text())
        assert report["watertight"]
        # marching cubes of the loaded field: the pipeline's raw surface
        assert report["raw"]["volume_mm3"] == pytest.approx(rec.raw_mesh.volume, rel=1e-9)
        volumes.append(report["final"]["volume_mm3"])
    assert volumes[0] == volumes[1]
    capsys.readouterr()


def _damage(arrays, name, value):
    out = dict(arrays)
    if value is None:
        del out[name]
    else:
        out[name] = value
    return out


@pytest.mark.parametrize("name, make, says", [
    ("field_values", lambda a: a["field_values"].astype(np.float64), "float64"),
    ("field_values", lambda a: a["field_values"][:-1], "expected float32"),
    ("field_values", lambda a: np.where(a["field_values"] > 1.0, np.nan, a["field_values"]).astype(np.float32),
     "range"),
    ("field_states", lambda a: np.where(a["field_states"] == 1, 3, a["field_states"]).astype(np.int8), "values other"),
    ("field_states", lambda a: a["field_states"][:, :, :-1], "expected int8"),
    ("field_states", lambda a: a["field_states"].astype(np.int32), "int32"),
    ("field_block", lambda a: np.int64(0), "integer"),
    ("field_block", lambda a: None, "missing"),
])
def test_damaged_arrays_give_one_line(rec, folders, tmp_path, name, make, says, capsys):
    new, _ = folders
    with np.load(new / "voxels.npz", allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    np.savez_compressed(tmp_path / "voxels.npz", **_damage(arrays, name, make(arrays)))
    with pytest.raises(OrganlabError) as e:
        load_voxels(tmp_path)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{tmp_path / 'voxels.npz'}: {name}: ")
    assert says in msg and msg.endswith("rewrite it with 'organlab reconstruct'")
    assert main(["mesh", str(tmp_path)]) == 2  # the CLI prints the line, no traceback
    err = capsys.readouterr().err
    assert f"{name}: " in err and "Traceback" not in err


def test_a_truncated_or_wrong_old_file_gives_one_line(rec, folders, tmp_path):
    new, _ = folders
    data = (new / "voxels.npz").read_bytes()
    (tmp_path / "voxels.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(OrganlabError, match=r"voxels\.npz: unreadable .*; rewrite it with 'organlab reconstruct'$"):
        load_voxels(tmp_path)
    np.savez_compressed(tmp_path / "voxels.npz", occupancy=rec.occupancy, origin_mm=np.asarray(rec.grid.origin),
                        voxel_size_mm=np.float64(2.0), field=np.asarray(rec.field)[:-1])
    with pytest.raises(OrganlabError, match=r"voxels\.npz: field: shape \(69, 70, 100\), expected"):
        load_voxels(tmp_path)
