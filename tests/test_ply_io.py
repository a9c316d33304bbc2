"""3DGS PLY writer/reader: round trip, plyfile compatibility, nerfstudio's exact layout."""

import os
from collections import OrderedDict

import numpy as np
import pytest
from plyfile import PlyData

from votesplat_ns.core.ply_io import (
    MIN_OPACITY_LOGIT,
    gaussian_property_names,
    gaussian_vertex_table,
    read_gaussian_ply,
    read_ply_header,
    read_vertex_ply,
    write_gaussian_table,
    write_instance_id_file,
    write_vertex_ply,
)


def random_params(n=50, k=15, seed=0):
    rng = np.random.default_rng(seed)
    return {
        "means": rng.normal(size=(n, 3)).astype(np.float32),
        "features_dc": rng.normal(size=(n, 3)).astype(np.float32),
        "features_rest": rng.normal(size=(n, k, 3)).astype(np.float32),
        "opacity_logits": rng.uniform(-3, 3, size=n).astype(np.float32),
        "log_scales": rng.normal(-3, 1, size=(n, 3)).astype(np.float32),
        "quats": rng.normal(size=(n, 4)).astype(np.float32),
    }


def write(path, p, **kwargs):
    table = gaussian_vertex_table(
        p["means"], p["features_dc"], p["features_rest"], p["opacity_logits"], p["log_scales"], p["quats"]
    )
    return write_gaussian_table(path, table, **kwargs)


def test_round_trip_every_field_with_plyfile(tmp_path):
    p = random_params()
    p["features_dc"][3, 1] = np.nan  # dropped: non-finite
    p["log_scales"][7, 0] = np.inf  # dropped: non-finite
    p["means"][11, 2] = np.nan  # dropped alone (nerfstudio would drop every vertex here)
    p["opacity_logits"][20] = MIN_OPACITY_LOGIT - 0.01  # dropped: rasteriser skips it
    p["opacity_logits"][21] = MIN_OPACITY_LOGIT + 0.01  # kept
    written = write(tmp_path / "a.ply", p)
    expected_rows = np.setdiff1d(np.arange(50), [3, 7, 11, 20])
    np.testing.assert_array_equal(written, expected_rows)

    vertex = PlyData.read(str(tmp_path / "a.ply"))["vertex"]
    names = [prop.name for prop in vertex.properties]
    assert names == gaussian_property_names(15)
    assert all(vertex.data.dtype[name] == np.dtype("<f4") for name in names)
    rest = p["features_rest"][expected_rows].transpose(0, 2, 1).reshape(len(expected_rows), 45)  # channel-major
    expected = {
        "x": p["means"][expected_rows, 0],
        "y": p["means"][expected_rows, 1],
        "z": p["means"][expected_rows, 2],
        "nx": 0,
        "ny": 0,
        "nz": 0,
        "opacity": p["opacity_logits"][expected_rows],
    }
    expected.update({f"f_dc_{i}": p["features_dc"][expected_rows, i] for i in range(3)})
    expected.update({f"f_rest_{i}": rest[:, i] for i in range(45)})
    expected.update({f"scale_{i}": p["log_scales"][expected_rows, i] for i in range(3)})
    expected.update({f"rot_{i}": p["quats"][expected_rows, i] for i in range(4)})
    for name in names:
        np.testing.assert_array_equal(
            vertex[name], np.broadcast_to(expected[name], (len(expected_rows),)), err_msg=name
        )

    back = read_gaussian_ply(tmp_path / "a.ply")
    for key in ("means", "features_dc", "features_rest", "log_scales", "quats", "opacity_logits"):
        np.testing.assert_array_equal(back[key], p[key][expected_rows], err_msg=key)


def test_select_and_no_filter(tmp_path):
    p = random_params(n=10, k=0)
    p["opacity_logits"][2] = -10.0
    written = write(tmp_path / "s.ply", p, select=np.array([5, 2, 9]), filter_invalid=False)
    np.testing.assert_array_equal(written, [5, 2, 9])
    back = read_gaussian_ply(tmp_path / "s.ply")
    assert back["features_rest"].shape == (3, 0, 3)
    np.testing.assert_array_equal(back["means"], p["means"][[5, 2, 9]])
    mask = np.zeros(10, bool)
    mask[[1, 2, 3]] = True
    np.testing.assert_array_equal(write(tmp_path / "m.ply", p, select=mask), [1, 3])


def test_empty_ply_is_valid(tmp_path):
    p = random_params(n=4, k=3)
    assert write(tmp_path / "e.ply", p, select=np.zeros(4, bool)).size == 0
    assert PlyData.read(str(tmp_path / "e.ply"))["vertex"].count == 0
    assert read_gaussian_ply(tmp_path / "e.ply")["means"].shape == (0, 3)


def test_header_and_bytes_match_nerfstudio_writer(tmp_path):
    # nerfstudio's own writer, fed the columns exactly as ExportGaussianSplat.main builds them
    from nerfstudio.scripts.exporter import ExportGaussianSplat

    p = random_params(n=6, k=15, seed=3)
    n = 6
    columns = OrderedDict()
    for i, axis in enumerate("xyz"):
        columns[axis] = p["means"][:, i]
    for axis in ("nx", "ny", "nz"):
        columns[axis] = np.zeros(n, dtype=np.float32)
    for i in range(3):
        columns[f"f_dc_{i}"] = p["features_dc"][:, i, None]
    rest = p["features_rest"].transpose(0, 2, 1).reshape(n, -1)
    for i in range(rest.shape[1]):
        columns[f"f_rest_{i}"] = rest[:, i, None]
    columns["opacity"] = p["opacity_logits"][:, None]
    for i in range(3):
        columns[f"scale_{i}"] = p["log_scales"][:, i, None]
    for i in range(4):
        columns[f"rot_{i}"] = p["quats"][:, i, None]
    ExportGaussianSplat.write_ply(str(tmp_path / "ns.ply"), n, columns)
    write(tmp_path / "ours.ply", p)

    fmt, count, props, comments, ns_offset = read_ply_header(tmp_path / "ns.ply")
    ours = read_ply_header(tmp_path / "ours.ply")
    assert (fmt, count, props) == ours[:3]
    assert "Vertical Axis: z" in ours[3]
    assert (tmp_path / "ns.ply").read_bytes()[ns_offset:] == (tmp_path / "ours.ply").read_bytes()[ours[4] :]


def test_vertex_ply_and_instance_ids(tmp_path):
    ids = np.array([3, -1, 0, 7], dtype=np.int64)
    xyz = np.arange(12, dtype=np.float32).reshape(4, 3)
    write_vertex_ply(
        tmp_path / "ids.ply", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "instance_id": ids.astype(np.int32)}
    )
    data = PlyData.read(str(tmp_path / "ids.ply"))["vertex"]
    np.testing.assert_array_equal(data["instance_id"], ids)
    assert read_vertex_ply(tmp_path / "ids.ply")["instance_id"].dtype == np.int32
    write_instance_id_file(tmp_path / "ids.npy", ids)
    loaded = np.load(tmp_path / "ids.npy")
    assert loaded.dtype == np.int32 and loaded.tolist() == ids.tolist()


def test_bad_input_leaves_existing_file_untouched(tmp_path):
    p = random_params(n=5)
    write(tmp_path / "keep.ply", p)
    before = (tmp_path / "keep.ply").read_bytes()
    bad = dict(p, quats=p["quats"][:, :3])  # fails validation before anything is opened
    with pytest.raises(ValueError, match="quats must have shape"):
        write(tmp_path / "keep.ply", bad)
    assert (tmp_path / "keep.ply").read_bytes() == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["keep.ply"]  # no temp files left


def test_failed_write_leaves_no_partial_file(tmp_path):
    from votesplat_ns.core.ply_io import atomic_write

    (tmp_path / "f.bin").write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_write(tmp_path / "f.bin") as handle:
            handle.write(b"half")
            raise RuntimeError("interrupted")
    assert (tmp_path / "f.bin").read_bytes() == b"old"
    assert [x.name for x in tmp_path.iterdir()] == ["f.bin"]


@pytest.mark.parametrize("umask, expected", [(0o022, 0o644), (0o077, 0o600)])
def test_atomic_write_follows_the_umask(tmp_path, umask, expected):
    from votesplat_ns.core.ply_io import atomic_write

    (tmp_path / "old.bin").write_bytes(b"old")
    previous = os.umask(umask)
    try:
        for name in ("new.bin", "old.bin"):
            with atomic_write(tmp_path / name) as handle:
                handle.write(b"data")
    finally:
        os.umask(previous)
    for name in ("new.bin", "old.bin"):
        assert (tmp_path / name).stat().st_mode & 0o777 == expected, name
        assert (tmp_path / name).read_bytes() == b"data"


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda p: p.update(means=p["means"][:, :2]), "means must have shape"),
        (lambda p: p.update(features_dc=p["features_dc"][:-1]), "features_dc must have shape"),
        (lambda p: p.update(features_rest=p["features_rest"][:, :, :2]), "features_rest must have shape"),
        (lambda p: p.update(opacity_logits=p["opacity_logits"][:-1]), "opacity_logits must have shape"),
    ],
)
def test_bad_shapes_are_clear_errors(tmp_path, change, message):
    p = random_params(n=5)
    change(p)
    with pytest.raises(ValueError, match=message):
        write(tmp_path / "x.ply", p)


def test_reader_rejects_non_gaussian_ply(tmp_path):
    write_vertex_ply(tmp_path / "pts.ply", {"x": np.zeros(2, np.float32)})
    with pytest.raises(ValueError, match="missing properties"):
        read_gaussian_ply(tmp_path / "pts.ply")
    (tmp_path / "txt.ply").write_text("hello\n")
    with pytest.raises(ValueError, match="not a PLY file"):
        read_gaussian_ply(tmp_path / "txt.ply")


def test_3dgs_reader_names_a_file_without_gaussians(tmp_path):
    from votesplat_ns.core.ply_io import GaussianPlyError, read_3dgs_ply

    write_vertex_ply(tmp_path / "pts.ply", {"x": np.zeros(2, np.float32)})
    with pytest.raises(GaussianPlyError, match=r"pts\.ply is not a 3DGS PLY: it lacks the properties"):
        read_3dgs_ply(tmp_path / "pts.ply")
