"""Retrofit from a standard 3DGS PLY: the strict reader, frame maths, frame checks, and end-to-end runs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import BIN, DEMO_SCENE, assert_offsets_beat_zero, train_votesplat
from gsplat.cuda._torch_impl import _quat_scale_to_covar_preci, _spherical_harmonics
from nerfstudio.utils.eval_utils import eval_setup

from votesplat_ns.core.ply_io import (
    MIN_OPACITY_LOGIT,
    GaussianPlyError,
    gaussian_vertex_table,
    read_3dgs_ply,
    write_gaussian_table,
    write_vertex_ply,
)
from votesplat_ns.errors import VoteSplatInputError
from votesplat_ns.ns.rasterizer import rasterize
from votesplat_ns.ns.retrofit import (
    RetrofitReference,
    applied_transform_of,
    frames_from_dataparser,
    homogeneous,
    resolve_frame,
    retrofit_reference,
    rotation_to_quaternion,
    similarity_parts,
    transform_gaussians,
)
from votesplat_ns.ns.run import SPLAT_PARAM_NAMES, latest_checkpoint, load_gaussians

NS_TRAIN = BIN / "ns-train"


def random_gaussians(n=40, sh_degree=3, seed=0):
    """splatfacto-shaped parameters (torch, float32)."""
    rng = np.random.default_rng(seed)
    k = (sh_degree + 1) ** 2 - 1
    t = lambda a: torch.tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    return {
        "means": t(rng.normal(size=(n, 3))),
        "scales": t(rng.normal(-3, 0.5, size=(n, 3))),
        "quats": t(rng.normal(size=(n, 4))),
        "features_dc": t(rng.normal(size=(n, 3))),
        "features_rest": t(rng.normal(0, 0.3, size=(n, k, 3))),
        "opacities": t(rng.uniform(-2, 3, size=(n, 1))),
    }


def write_ply(path, g, select=None):
    table = gaussian_vertex_table(
        g["means"], g["features_dc"], g["features_rest"], g["opacities"], g["scales"], g["quats"]
    )
    return write_gaussian_table(path, table, select=select, filter_invalid=False)


def random_rotation(seed=1):
    q = torch.tensor(np.random.default_rng(seed).normal(size=4), dtype=torch.float64)
    q = q / q.norm()
    w, x, y, z = q.tolist()
    return torch.tensor(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ],
        dtype=torch.float64,
    )


# ------------------------------------------------------------------ the strict reader


def test_reader_reads_every_writers_layout(tmp_path):
    g = random_gaussians()
    write_ply(tmp_path / "ns.ply", g)  # ns-export gaussian-splat's exact layout (test_export checks the bytes)
    arrays, degree = read_3dgs_ply(tmp_path / "ns.ply")
    assert degree == 3
    np.testing.assert_array_equal(arrays["features_rest"], g["features_rest"].numpy())
    np.testing.assert_array_equal(arrays["opacity_logits"], g["opacities"].numpy()[:, 0])

    # gsplat's export_splats: no normals; INRIA's writer may store doubles; property order is free
    rest = g["features_rest"].numpy().transpose(0, 2, 1).reshape(40, 45)  # channel-major, as every writer
    columns = {"rot_0": g["quats"][:, 0].numpy().astype(np.float64)}
    columns.update({c: g["means"][:, i].numpy() for i, c in enumerate("xyz")})
    columns.update({f"f_dc_{i}": g["features_dc"][:, i].numpy() for i in range(3)})
    columns.update({f"f_rest_{i}": rest[:, i] for i in range(45)})
    columns["opacity"] = g["opacities"][:, 0].numpy()
    columns.update({f"scale_{i}": g["scales"][:, i].numpy() for i in range(3)})
    columns.update({f"rot_{i}": g["quats"][:, i].numpy() for i in range(1, 4)})
    write_vertex_ply(tmp_path / "gsplat.ply", columns)
    other, degree = read_3dgs_ply(tmp_path / "gsplat.ply")
    assert degree == 3
    for name in arrays:
        np.testing.assert_array_equal(other[name], arrays[name], err_msg=name)

    g0 = random_gaussians(sh_degree=0)
    write_ply(tmp_path / "dc.ply", g0)
    arrays, degree = read_3dgs_ply(tmp_path / "dc.ply")
    assert degree == 0 and arrays["features_rest"].shape == (40, 0, 3)


@pytest.mark.parametrize("chunk_rows", [1, 7, 40, 1000])
def test_reader_in_chunks_of_any_size_reads_any_float_order(tmp_path, chunk_rows):
    # all float32 in a shuffled order, no normals, vote offsets (not read, so their NaNs are fine) in between
    g = random_gaussians()
    rest = g["features_rest"].numpy().transpose(0, 2, 1).reshape(40, 45)
    columns = {c: g["means"][:, i].numpy() for i, c in enumerate("xyz")}
    columns.update({f"f_dc_{i}": g["features_dc"][:, i].numpy() for i in range(3)})
    columns.update({f"f_rest_{i}": rest[:, i] for i in range(45)})
    columns["opacity"] = g["opacities"][:, 0].numpy()
    columns.update({f"scale_{i}": g["scales"][:, i].numpy() for i in range(3)})
    columns.update({f"rot_{i}": g["quats"][:, i].numpy() for i in range(4)})
    columns.update({f"vote_offset_{i}": np.full(40, np.nan, np.float32) for i in range(3)})
    order = list(columns)
    np.random.default_rng(3).shuffle(order)
    write_vertex_ply(tmp_path / "shuffled.ply", {name: columns[name] for name in order})
    arrays, degree = read_3dgs_ply(tmp_path / "shuffled.ply", chunk_rows=chunk_rows)
    assert degree == 3
    expected = {
        "means": g["means"],
        "features_dc": g["features_dc"],
        "features_rest": g["features_rest"],
        "opacity_logits": g["opacities"][:, 0],
        "log_scales": g["scales"],
        "quats": g["quats"],
    }
    assert list(arrays) == list(expected)
    for name, value in expected.items():
        assert arrays[name].dtype == np.float32 and arrays[name].flags.c_contiguous, name
        np.testing.assert_array_equal(arrays[name], value.numpy(), err_msg=name)

    # a value that is not finite in a later chunk is found, and named as in a file read whole
    columns["scale_2"] = columns["scale_2"].copy()
    columns["scale_2"][33] = np.inf
    write_vertex_ply(tmp_path / "inf.ply", {name: columns[name] for name in order})
    with pytest.raises(GaussianPlyError, match=r"1 of 40 Gaussians have NaN or infinite values \(in scale_2\)"):
        read_3dgs_ply(tmp_path / "inf.ply", chunk_rows=chunk_rows)


def _bad_files(tmp_path):
    g = random_gaussians(n=8)
    write_ply(tmp_path / "good.ply", g)
    good = (tmp_path / "good.ply").read_bytes()
    header_end = good.index(b"end_header\n") + len(b"end_header\n")
    files = {}

    def columns(drop=(), add=None):
        arrays, _ = read_3dgs_ply(tmp_path / "good.ply")
        rest = arrays["features_rest"].transpose(0, 2, 1).reshape(8, -1)
        cols = {c: arrays["means"][:, i] for i, c in enumerate("xyz")}
        cols.update({f"f_dc_{i}": arrays["features_dc"][:, i] for i in range(3)})
        cols.update({f"f_rest_{i}": rest[:, i] for i in range(rest.shape[1])})
        cols["opacity"] = arrays["opacity_logits"]
        cols.update({f"scale_{i}": arrays["log_scales"][:, i] for i in range(3)})
        cols.update({f"rot_{i}": arrays["quats"][:, i] for i in range(4)})
        for name in drop:
            cols.pop(name)
        cols.update(add or {})
        return cols

    files["missing"] = (columns(drop=["rot_3"]), "lacks the properties rot_3")
    files["extra"] = (
        columns(add={"filter_3D": np.ones(8, np.float32)}),
        "properties a standard 3DGS PLY does not have (filter_3D)",
    )
    rgb = columns(drop=["f_dc_0", "f_dc_1", "f_dc_2"], add={c: np.zeros(8, np.uint8) for c in ("red", "green", "blue")})
    files["rgb"] = (rgb, "--ply-color-mode sh_coeffs")
    files["rest_count"] = (
        columns(drop=[f"f_rest_{i}" for i in range(10, 45)]),
        "10 f_rest_* properties, which fits no SH degree",
    )
    nan = columns()
    nan["scale_1"] = nan["scale_1"].copy()
    nan["scale_1"][[2, 5]] = np.nan
    nan["x"] = nan["x"].copy()
    nan["x"][5] = np.inf
    files["nan"] = (nan, "2 of 8 Gaussians have NaN or infinite values (in x, scale_1)")
    for name, (cols, message) in files.items():
        write_vertex_ply(tmp_path / f"{name}.ply", cols)
        files[name] = (tmp_path / f"{name}.ply", message)

    (tmp_path / "empty.ply").write_bytes(good[:header_end].replace(b"element vertex 8", b"element vertex 0"))
    files["empty"] = (tmp_path / "empty.ply", "holds no Gaussians")
    (tmp_path / "truncated.ply").write_bytes(good[: header_end + 3 * 62 * 4 + 7])
    files["truncated"] = (tmp_path / "truncated.ply", "is truncated: its header declares 8 Gaussians")
    (tmp_path / "image.ply").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4)
    files["not_ply"] = (tmp_path / "image.ply", "is not a PLY file")
    (tmp_path / "cut_header.ply").write_bytes(good[: header_end // 2])
    files["cut_header"] = (tmp_path / "cut_header.ply", "no end_header line")
    ascii_header = good[:header_end].replace(b"binary_little_endian", b"ascii")
    (tmp_path / "ascii.ply").write_bytes(ascii_header + b"0 " * 62 * 7 + b"\n")  # 7 of 8 vertices, on one line
    files["ascii"] = (tmp_path / "ascii.ply", "vertex lines hold 434 values, the header declares 62 properties")
    (tmp_path / "ascii_cut.ply").write_bytes(ascii_header + b"0 " * 62 + b"\n" + b"1 " * 62 + b"\n")
    files["ascii_cut"] = (tmp_path / "ascii_cut.ply", "is truncated: its header declares 8 Gaussians but only 2 follow")
    (tmp_path / "ascii_text.ply").write_bytes(ascii_header + b"zero " * 62 + b"\n")
    files["ascii_text"] = (tmp_path / "ascii_text.ply", "its vertex values cannot be read")
    return files


BAD_FILES = [
    "missing",
    "extra",
    "rgb",
    "rest_count",
    "nan",
    "empty",
    "truncated",
    "not_ply",
    "cut_header",
    "ascii",
    "ascii_cut",
    "ascii_text",
]


@pytest.mark.parametrize("case", BAD_FILES)
def test_bad_ply_is_one_clear_line(tmp_path, case):
    path, message = _bad_files(tmp_path)[case]
    with pytest.raises(GaussianPlyError) as info:
        read_3dgs_ply(path)
    text = str(info.value)
    assert message in text, text
    assert str(path) in text and "\n" not in text
    assert "3DGS" in text or "again" in text, text  # says what to give instead


# ------------------------------------------------------------------ frame maths


def test_a_rigid_frame_change_keeps_what_every_camera_sees():
    g = random_gaussians(n=30)
    rotation, scale, shift = random_rotation(), 2.5, torch.tensor([0.3, -1.0, 4.0], dtype=torch.float64)
    matrix = torch.eye(4, dtype=torch.float64)
    matrix[:3, :3], matrix[:3, 3] = scale * rotation, shift
    moved = transform_gaussians(g, matrix)
    R = rotation.float()

    torch.testing.assert_close(moved["means"], scale * g["means"] @ R.T + shift.float())
    # covariance: s^2 R S R^T
    cov = _quat_scale_to_covar_preci(
        g["quats"] / g["quats"].norm(dim=-1, keepdim=True), torch.exp(g["scales"]), compute_preci=False
    )[0]
    cov_moved = _quat_scale_to_covar_preci(
        moved["quats"] / moved["quats"].norm(dim=-1, keepdim=True), torch.exp(moved["scales"]), compute_preci=False
    )[0]
    torch.testing.assert_close(cov_moved, scale**2 * R @ cov @ R.T, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(moved["quats"].norm(dim=-1), g["quats"].norm(dim=-1))
    # view-dependent colour: the moved scene seen along R d looks as the original along d
    dirs = torch.randn(30, 3)
    coeffs = torch.cat([g["features_dc"][:, None], g["features_rest"]], 1)
    coeffs_moved = torch.cat([moved["features_dc"][:, None], moved["features_rest"]], 1)
    torch.testing.assert_close(
        _spherical_harmonics(3, dirs @ R.T, coeffs_moved), _spherical_harmonics(3, dirs, coeffs), rtol=1e-4, atol=1e-5
    )
    assert not torch.allclose(moved["features_rest"], g["features_rest"], atol=1e-2)

    back = transform_gaussians(moved, torch.linalg.inv(matrix))
    for name in g:
        if name == "quats":  # q and -q are the same rotation
            sign = torch.sign((back[name] * g[name]).sum(-1, keepdim=True))
            torch.testing.assert_close(back[name] * sign, g[name], rtol=1e-4, atol=1e-5)
        else:
            torch.testing.assert_close(back[name], g[name], rtol=1e-4, atol=1e-5)


def test_quaternion_of_a_rotation_and_non_similarities():
    for seed in range(5):
        R = random_rotation(seed)
        q = rotation_to_quaternion(R)
        w, x, y, z = q.tolist()
        rebuilt = torch.tensor(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ],
            dtype=torch.float64,
        )
        torch.testing.assert_close(rebuilt, R)
    with pytest.raises(ValueError, match="mirrors"):
        similarity_parts(torch.diag(torch.tensor([1.0, 1.0, -1.0, 1.0])))
    with pytest.raises(ValueError, match="not a rotation and uniform scale"):
        similarity_parts(torch.diag(torch.tensor([1.0, 2.0, 1.0, 1.0])))


@pytest.mark.parametrize("applied_scale", [1.0, 0.25])
def test_frames_follow_nerfstudios_dataparser(tmp_path, applied_scale):
    """Frames as nerfstudio defines them: transforms.json poses = applied_scale (A p_colmap); its dataparser maps
    them by s (T p) and reports T A as dataparser_transform and s * applied_scale as dataparser_scale."""
    applied = torch.tensor([[0.0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0]], dtype=torch.float64)  # ns-process-data's
    meta = {"applied_transform": applied.tolist(), "frames": []}
    if applied_scale != 1.0:
        meta["applied_scale"] = applied_scale
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    read_transform, read_scale = applied_transform_of(tmp_path)
    torch.testing.assert_close(read_transform, applied)
    assert read_scale == applied_scale
    assert applied_transform_of(DEMO_SCENE) == (None, 1.0)

    T = homogeneous(torch.cat([random_rotation(3), torch.tensor([[0.1], [0.2], [-0.7]], dtype=torch.float64)], 1))
    s = 0.4
    frames = frames_from_dataparser((T @ homogeneous(applied))[:3], s * applied_scale, applied, applied_scale)
    point_colmap = torch.tensor([1.0, 2.0, 3.0, 1.0], dtype=torch.float64)
    point_dataset = torch.cat(
        [applied_scale * (homogeneous(applied) @ point_colmap)[:3], torch.ones(1, dtype=torch.float64)]
    )
    expected = s * (T @ point_dataset)[:3]
    torch.testing.assert_close((frames["dataset"] @ point_dataset)[:3], expected)
    torch.testing.assert_close((frames["colmap"] @ point_colmap)[:3], expected)
    torch.testing.assert_close(frames["dataparser"], torch.eye(4, dtype=torch.float64))


# ------------------------------------------------------------------ on the bundled scene, with a trained demo


def trained_gaussians(config_path: Path):
    return {name: value.float() for name, value in load_gaussians(latest_checkpoint(config_path.parent)).items()}


def exported_rows(gaussians):
    """The rows ns-export gaussian-splat keeps: finite, opacity logit >= logit(1/255)."""
    finite = torch.stack([torch.isfinite(v.reshape(v.shape[0], -1)).all(1) for v in gaussians.values()]).all(0)
    return finite & (gaussians["opacities"][:, 0] >= MIN_OPACITY_LOGIT)


@pytest.fixture(scope="module")
def demo_reference(trained_demo):
    config = yaml.load(Path(trained_demo).read_text(), Loader=yaml.Loader)
    datamanager = config.pipeline.datamanager.setup(device="cpu", test_mode="test")
    return retrofit_reference(datamanager)


@pytest.fixture(scope="module")
def ns_exported_ply(trained_demo, tmp_path_factory):
    """splat.ply written by nerfstudio's own ``ns-export gaussian-splat`` from the trained demo."""
    from nerfstudio.scripts.exporter import ExportGaussianSplat

    out = tmp_path_factory.mktemp("ns_export")
    ExportGaussianSplat(load_config=Path(trained_demo), output_dir=out).main()
    return out / "splat.ply"


@pytest.fixture(scope="module")
def dataset_frame_ply(trained_demo, tmp_path_factory):
    """The trained demo's Gaussians in the frame of transforms.json, from the run's dataparser_transforms.json."""
    saved = json.loads((Path(trained_demo).parent / "dataparser_transforms.json").read_text())
    to_training = torch.diag(torch.tensor([saved["scale"]] * 3 + [1.0], dtype=torch.float64)) @ homogeneous(
        torch.tensor(saved["transform"])
    )
    g = trained_gaussians(Path(trained_demo))
    path = tmp_path_factory.mktemp("dataset_frame") / "scene.ply"
    write_ply(path, transform_gaussians(g, torch.linalg.inv(to_training)), select=exported_rows(g))
    return path, to_training


def test_frame_checks_on_the_demo_scene(demo_reference, trained_demo, ns_exported_ply, dataset_frame_ply):
    ns_ply, (ds_ply, _) = ns_exported_ply, dataset_frame_ply
    g = trained_gaussians(Path(trained_demo))
    keep = exported_rows(g)
    from votesplat_ns.ns.run import gaussians_from_ply_arrays

    def load(path):
        return gaussians_from_ply_arrays(read_3dgs_ply(path)[0])

    frame, moved, fits = resolve_frame(load(ns_ply), demo_reference, "auto", ns_ply, rasterize, 3)
    assert frame == "dataparser"
    torch.testing.assert_close(moved["means"], g["means"][keep])
    by_name = {fit.name: fit for fit in fits}
    assert by_name["dataset"].same_as == ["colmap"]  # the demo's transforms.json has no applied_transform
    # both frames put every Gaussian in view: only the photos tell them apart
    assert by_name["dataparser"].in_view_share > 0.9 and by_name["dataset"].in_view_share > 0.9
    assert by_name["dataparser"].psnr > by_name["dataset"].psnr + 3

    frame, moved, _ = resolve_frame(load(ds_ply), demo_reference, "auto", ds_ply, rasterize, 3)
    assert frame == "dataset"
    torch.testing.assert_close(moved["means"], g["means"][keep], rtol=1e-5, atol=2e-6)

    with pytest.raises(
        VoteSplatInputError, match=r"is not in frame 'dataset'.*pass --pipeline.model.retrofit-frame dataparser$"
    ):
        resolve_frame(load(ns_ply), demo_reference, "dataset", ns_ply, rasterize, 3)
    with pytest.raises(
        VoteSplatInputError,
        match=r"only \d+\.\d% of the Gaussians of .* in frame 'dataparser'.*retrofit-frame dataset$",
    ):
        resolve_frame(load(ds_ply), demo_reference, "dataparser", ds_ply, rasterize, 3)

    far = load(ns_ply)
    far["means"] = far["means"] + 100.0  # a scene of somewhere else: nothing in view in any frame
    with pytest.raises(
        VoteSplatInputError, match=r"only 0\.0% of the Gaussians of .* project into the training views in any frame"
    ):
        resolve_frame(far, demo_reference, "auto", ns_ply, rasterize, 3)

    # two different frames that render the views equally well: auto refuses to guess
    nudged = torch.eye(4, dtype=torch.float64)
    nudged[2, 3] = 0.01
    twins = RetrofitReference(
        {"dataparser": torch.eye(4, dtype=torch.float64), "dataset": nudged}, demo_reference.views
    )
    with pytest.raises(VoteSplatInputError, match=r"cannot tell the frame of .*: frames '\w+' and '\w+' both fit"):
        resolve_frame(load(ns_ply), twins, "auto", ns_ply, rasterize, 3)


def test_auto_finds_the_colmap_frame_of_a_capture_with_an_applied_transform(trained_demo, tmp_path):
    """The demo capture as ns-process-data would have made it from COLMAP: transforms.json records the axis
    permutation it applied; a PLY in COLMAP's world (as the original 3DGS writes it) is found as 'colmap'."""
    applied = torch.tensor([[0.0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0]], dtype=torch.float64)
    data = tmp_path / "capture"
    data.mkdir()
    for entry in DEMO_SCENE.iterdir():
        if entry.name != "transforms.json":
            (data / entry.name).symlink_to(entry)
    meta = json.loads((DEMO_SCENE / "transforms.json").read_text())
    meta["applied_transform"] = applied.tolist()
    (data / "transforms.json").write_text(json.dumps(meta))
    config = yaml.load(Path(trained_demo).read_text(), Loader=yaml.Loader)
    config.pipeline.datamanager.data = data
    config.pipeline.datamanager.dataparser.data = data
    reference = retrofit_reference(config.pipeline.datamanager.setup(device="cpu", test_mode="test"))

    saved = json.loads((Path(trained_demo).parent / "dataparser_transforms.json").read_text())
    dataset_to_training = torch.diag(torch.tensor([saved["scale"]] * 3 + [1.0], dtype=torch.float64)) @ homogeneous(
        torch.tensor(saved["transform"])
    )
    g = trained_gaussians(Path(trained_demo))
    in_colmap = transform_gaussians(g, torch.linalg.inv(dataset_to_training @ homogeneous(applied)))
    frame, moved, fits = resolve_frame(in_colmap, reference, "auto", Path("colmap_world.ply"), rasterize, 3)
    assert frame == "colmap" and len(fits) == 3, fits
    torch.testing.assert_close(moved["means"], g["means"], rtol=1e-5, atol=2e-6)
    torch.testing.assert_close(moved["features_rest"], g["features_rest"], rtol=1e-4, atol=1e-5)


def _assert_retrofit_froze(config_path: Path, expected, frame: str):
    _, pipeline, _, _ = eval_setup(config_path, test_mode="val")
    model = pipeline.model
    assert model.retrofit_source_frame == frame
    for name in SPLAT_PARAM_NAMES:  # the same Gaussians as a retrofit from the checkpoint, frozen
        torch.testing.assert_close(model.gauss_params[name].data.cpu(), expected[name], rtol=1e-5, atol=2e-6, msg=name)
    support = model.gauss_params["vote_support"].data
    assert (support > 0).any(dim=0).all(), "every level must have received vote supervision"
    assert_offsets_beat_zero(pipeline)


def test_retrofit_from_ns_export_gaussian_splat(trained_demo, ns_exported_ply, tmp_path):
    g = trained_gaussians(Path(trained_demo))
    keep = exported_rows(g)
    config_path = train_votesplat(DEMO_SCENE, tmp_path, steps=30, vote_start=0, retrofit_from=ns_exported_ply)
    _assert_retrofit_froze(config_path, {name: g[name][keep] for name in SPLAT_PARAM_NAMES}, "dataparser")


def test_retrofit_from_a_ply_in_the_datasets_frame(trained_demo, dataset_frame_ply, tmp_path):
    path, _ = dataset_frame_ply
    g = trained_gaussians(Path(trained_demo))
    keep = exported_rows(g)
    config_path = train_votesplat(DEMO_SCENE, tmp_path, steps=30, vote_start=0, retrofit_from=path)
    _assert_retrofit_froze(config_path, {name: g[name][keep] for name in SPLAT_PARAM_NAMES}, "dataset")


def test_wrong_frame_stops_ns_train_before_training(ns_exported_ply, tmp_path):
    with pytest.raises(
        VoteSplatInputError, match=r"is not in frame 'dataset'.*pass --pipeline.model.retrofit-frame dataparser$"
    ):
        train_votesplat(
            DEMO_SCENE, tmp_path, steps=5, vote_start=0, retrofit_from=ns_exported_ply, retrofit_frame="dataset"
        )
    assert not list(tmp_path.rglob("*.ckpt"))


def test_ns_train_with_a_ply_of_another_sh_degree_is_one_line(trained_demo, tmp_path, run_console_script):
    g = trained_gaussians(Path(trained_demo))
    g["features_rest"] = g["features_rest"][:, :3]  # degree 1
    write_ply(tmp_path / "degree1.ply", g, select=exported_rows(g))
    command = [
        str(NS_TRAIN),
        "votesplat",
        "--data",
        str(DEMO_SCENE),
        "--vis",
        "tensorboard",
        "--max-num-iterations",
        "1",
        "--output-dir",
        str(tmp_path / "runs"),
        "--machine.device-type",
        "cpu",
        "--pipeline.model.retrofit-from",
        str(tmp_path / "degree1.ply"),
    ]
    result = run_console_script(command, cwd=tmp_path)
    assert result.returncode != 0 and "Traceback" not in result.stderr, result.stderr[-4000:]
    last = [line for line in result.stderr.splitlines() if line.strip()][-1]
    assert last.startswith("ns-train votesplat: error: --pipeline.model.retrofit-from "), last
    assert "has SH degree 1 (9 f_rest properties)" in last and "pass --pipeline.model.sh-degree 1" in last, last
    assert not list((tmp_path / "runs").rglob("*.ckpt"))


def test_degree_0_ply_colours_become_splatfacto_logits():
    # nerfstudio's exporter writes f_dc = RGB2SH(sigmoid(features_dc)) for a degree-0 splatfacto
    # (SplatfactoModel.shs_0); reading it back must give the same features_dc, so the retrofitted
    # model shows the same colours (splatfacto renders sigmoid(features_dc) at degree 0)
    from nerfstudio.models.splatfacto import RGB2SH

    from votesplat_ns.ns.run import splatfacto_dc_from_ply

    logits = torch.randn(200, 3, generator=torch.Generator().manual_seed(0)) * 2.0
    exported = RGB2SH(torch.sigmoid(logits))
    torch.testing.assert_close(splatfacto_dc_from_ply(exported, 0), logits, rtol=1e-4, atol=1e-4)
    # from degree 1 on both keep SH coefficients
    assert splatfacto_dc_from_ply(exported, 3) is exported
    # a writer's colour outside [0, 1] is clamped, not NaN
    assert torch.isfinite(splatfacto_dc_from_ply(torch.full((1, 3), 10.0), 0)).all()
