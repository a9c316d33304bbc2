"""Instance export: files and manifest, nerfstudio-identical scene PLY, errors, atomicity, CLI."""

import importlib
import json
import os
import shutil
import sys
import textwrap
import typing
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from test_instances import brute_force_rasterize  # noqa: E402  (tests/ is on sys.path under pytest)

import votesplat_ns.ns.export as export_module
import votesplat_ns.ns.instance_export as instance_export_module
from votesplat_ns.core.cameras import PinholeView, viewmat_from_camera_to_world
from votesplat_ns.core.clustering import ClusteringOptions
from votesplat_ns.core.instances import InstanceSet
from votesplat_ns.core.ply_io import read_gaussian_ply, read_ply_header
from votesplat_ns.core.scene import TrainedScene
from votesplat_ns.ns.export import ExportVoteSplatInstances
from votesplat_ns.ns.instance_export import export_instances
from votesplat_ns.ns.patches import SUBCOMMAND_NAME, install_ns_export_hook
from votesplat_ns.ns.run import LoadedRun

LEVELS = ("instance", "part")


def vote_scene(num_objects=4, per_object=240, num_background=300, sh_degree=3, seed=0):
    """splatfacto-style raw parameters of objects (two parts each) whose votes hit their centres."""
    rng = np.random.default_rng(seed)
    centres = np.array([[-1.5, -1.0, 0.0], [1.5, -1.0, 0.0], [-1.5, 1.0, 0.0], [1.5, 1.0, 0.0]])[:num_objects]
    object_of = np.repeat(np.arange(num_objects), per_object)
    fg = object_of.size
    means = centres[object_of] + rng.normal(0, 0.25, size=(fg, 3))
    part_of = object_of * 2 + (means[:, 0] > centres[object_of, 0])
    part_centres = np.stack([means[part_of == p].mean(0) for p in range(2 * num_objects)])
    means = np.concatenate([means, rng.uniform(-3, 3, size=(num_background, 3)) * [1, 1, 0.2] + [0, 0, -1.5]])
    n = means.shape[0]
    offsets = np.zeros((n, 2, 3))
    offsets[:fg, 0] = centres[object_of] - means[:fg] + rng.normal(0, 0.01, (fg, 3))
    offsets[:fg, 1] = part_centres[part_of] - means[:fg] + rng.normal(0, 0.01, (fg, 3))
    support = np.zeros((n, 2))
    support[:fg] = rng.integers(1, 9, size=(fg, 2))
    k = (sh_degree + 1) ** 2 - 1
    as_tensor = lambda a: torch.tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    params = {
        "means": as_tensor(means),
        "scales": as_tensor(rng.normal(-2.5, 0.2, size=(n, 3))),
        "quats": as_tensor(rng.normal(size=(n, 4))),
        "features_dc": as_tensor(rng.normal(size=(n, 3))),
        "features_rest": as_tensor(rng.normal(0, 0.1, size=(n, k, 3))),
        "opacities": as_tensor(rng.uniform(0.5, 3, size=(n, 1))),
        "vote_offsets": as_tensor(offsets),
        "vote_support": as_tensor(support),
    }
    return params, object_of


def export(params, out, **kwargs):
    kwargs.setdefault("level_names", LEVELS)
    kwargs.setdefault("progress", False)
    return export_instances(params, out, **kwargs)


def no_leftovers(parent: Path, keep=()):
    return sorted(p.name for p in parent.iterdir() if p.name not in keep) == []


def test_export_writes_a_consistent_folder(tmp_path):
    params, object_of = vote_scene()
    params["opacities"][5] = -8.0  # below logit(1/255): left out of every PLY, as ns-export does
    params["features_dc"][7, 0] = float("nan")
    out = tmp_path / "export"
    manifest = export(params, out, remove=[1])
    files = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert files == sorted(
        [
            "instances.json",
            "instance_ids.npz",
            "scene.ply",
            "scene_instance_ids.npy",
            "background.ply",
            "scene_without_1.ply",
        ]
        + [f"instances/instance_{i:04d}.ply" for i in range(4)]
    )
    assert json.loads((out / "instances.json").read_text()) == manifest
    assert manifest["level_names"] == list(LEVELS)
    level = manifest["levels"][0]
    assert level["num_instances"] == 4 and manifest["levels"][1]["num_instances"] == 8
    assert level["clustering"]["algorithm"] == "hdbscan" and level["clustering"]["min_cluster_size"] >= 10
    assert {i["parent"] for i in manifest["levels"][1]["instances"]} == {0, 1, 2, 3}

    n = params["means"].shape[0]
    scene = read_gaussian_ply(out / "scene.ply")
    ids = np.load(out / "scene_instance_ids.npy")
    assert manifest["export"]["ply_counts"]["scene"] == scene["means"].shape[0] == ids.shape[0] == n - 2
    instances = InstanceSet.load(out)
    written = np.setdiff1d(np.arange(n), [5, 7])
    np.testing.assert_array_equal(ids, instances.level("instance").ids[written])
    np.testing.assert_array_equal(scene["means"], params["means"].numpy()[written])
    # every instance file holds exactly its members (less the two filtered Gaussians)
    total = 0
    for entry in level["instances"]:
        ply = read_gaussian_ply(out / entry["file"])
        members = np.setdiff1d(instances.level(0).gaussian_indices(entry["id"]), [5, 7])
        np.testing.assert_array_equal(ply["means"], params["means"].numpy()[members])
        assert entry["ply_count"] == members.size == ply["means"].shape[0]
        assert len(set(object_of[members[members < object_of.size]])) == 1  # one true object per instance
        total += entry["ply_count"]
    background = read_gaussian_ply(out / "background.ply")["means"].shape[0]
    assert total + background == manifest["export"]["ply_counts"]["scene"]
    removed = manifest["export"]["removed"]
    assert removed["ids"] == [1] and removed["file"] == "scene_without_1.ply"
    without = read_gaussian_ply(out / "scene_without_1.ply")["means"].shape[0]
    assert (
        without
        == removed["ply_count"]
        == manifest["export"]["ply_counts"]["scene"] - level["instances"][1]["ply_count"]
    )
    assert manifest["export"]["picture"] is None


def test_export_picture_with_a_renderer(tmp_path):
    params, _ = vote_scene(num_background=0)
    K = torch.tensor([[24.0, 0, 20.0], [0, 24.0, 15.0], [0, 0, 1]])
    view = PinholeView(
        viewmat=torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 8], [0, 0, 0, 1]]), K=K, width=40, height=30
    )
    manifest = export(params, tmp_path / "out", views=[view, view], rasterize_fn=brute_force_rasterize)
    from PIL import Image

    picture = np.asarray(Image.open(tmp_path / "out" / manifest["export"]["picture"]))
    assert picture.shape == (30, 40 * 2 + 4, 3)
    colours = {tuple(i["color"]) for i in manifest["levels"][0]["instances"]}
    seen = {tuple(c) for c in picture[:, :40].reshape(-1, 3)}
    assert len(colours & seen) == 4  # all four objects are visible and drawn in their manifest colour


def fake_splatfacto(params, sh_degree):
    from nerfstudio.models.splatfacto import SplatfactoModel, SplatfactoModelConfig

    model = SplatfactoModel.__new__(SplatfactoModel)
    torch.nn.Module.__init__(model)
    model.config = SplatfactoModelConfig(sh_degree=sh_degree)
    model.gauss_params = torch.nn.ParameterDict(
        {k: torch.nn.Parameter(v.clone(), requires_grad=False) for k, v in params.items()}
    )
    return model


@pytest.mark.parametrize("sh_degree", [3, 0])
def test_scene_ply_is_identical_to_ns_export_gaussian_splat(tmp_path, monkeypatch, sh_degree):
    import nerfstudio.scripts.exporter as ns_exporter

    params, _ = vote_scene(num_objects=2, per_object=120, num_background=40, sh_degree=sh_degree)
    params["opacities"][3] = -6.0  # nerfstudio drops it (opacity below 1/255)
    params["scales"][4, 2] = float("inf")  # nerfstudio drops it (non-finite)
    model = fake_splatfacto(params, sh_degree)
    monkeypatch.setattr(ns_exporter, "eval_setup", lambda *a, **k: (None, SimpleNamespace(model=model), None, None))
    ns_exporter.ExportGaussianSplat(load_config=Path("unused.yml"), output_dir=tmp_path / "ns").main()
    export_instances(model, tmp_path / "ours", level_names=LEVELS, progress=False)

    ns_header = read_ply_header(tmp_path / "ns" / "splat.ply")
    our_header = read_ply_header(tmp_path / "ours" / "scene.ply")
    assert ns_header[0:3] == our_header[0:3]  # format, vertex count, (name, type) of every property
    assert ns_header[1] == params["means"].shape[0] - 2
    ns_body = (tmp_path / "ns" / "splat.ply").read_bytes()[ns_header[4] :]
    assert ns_body == (tmp_path / "ours" / "scene.ply").read_bytes()[our_header[4] :]


def test_reexport_replaces_a_previous_export(tmp_path):
    params, _ = vote_scene()
    out = tmp_path / "out"
    export(params, out, remove=[0, 2])
    assert (out / "scene_without_0_2.ply").is_file()
    manifest = export(params, out, level="part")
    assert not (out / "scene_without_0_2.ply").exists()  # the whole folder was replaced
    assert manifest["export"]["level"] == "part" and len(list((out / "instances").iterdir())) == 8
    assert no_leftovers(tmp_path, keep=["out"])


def test_an_interrupted_export_leaves_nothing_half_written(tmp_path, monkeypatch):
    params, _ = vote_scene()
    real_write = instance_export_module.write_gaussian_table
    calls = []

    def failing_write(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise OSError("disk full")
        return real_write(*args, **kwargs)

    monkeypatch.setattr(instance_export_module, "write_gaussian_table", failing_write)
    with pytest.raises(OSError, match="disk full"):
        export(params, tmp_path / "fresh")
    assert no_leftovers(tmp_path)

    monkeypatch.setattr(instance_export_module, "write_gaussian_table", real_write)
    export(params, tmp_path / "old")
    before = (tmp_path / "old" / "instances.json").read_bytes()
    calls.clear()
    monkeypatch.setattr(instance_export_module, "write_gaussian_table", failing_write)
    with pytest.raises(OSError):
        export(params, tmp_path / "old", remove=[0])
    assert (tmp_path / "old" / "instances.json").read_bytes() == before
    assert not (tmp_path / "old" / "scene_without_0.ply").exists()
    assert no_leftovers(tmp_path, keep=["old"])


@pytest.mark.parametrize("umask, file_mode, folder_mode", [(0o022, 0o644, 0o755), (0o077, 0o600, 0o700)])
def test_export_files_and_folders_follow_the_umask(tmp_path, umask, file_mode, folder_mode):
    params, _ = vote_scene()
    previous = os.umask(umask)
    try:
        export(params, tmp_path / "out", remove=[0])
        export(params, tmp_path / "out", remove=[1])  # a re-export replaces the folder: same modes
    finally:
        os.umask(previous)
    out = tmp_path / "out"
    modes = {str(p.relative_to(tmp_path)): p.stat().st_mode & 0o777 for p in [out, *out.rglob("*")]}
    assert len(modes) == 12 and (out / "scene_without_1.ply").is_file()
    for name, mode in modes.items():
        expected = folder_mode if (tmp_path / name).is_dir() else file_mode
        assert mode == expected, f"{name}: {oct(mode)} != {oct(expected)}"
    assert no_leftovers(tmp_path, keep=["out"])


def splatfacto_params():
    params, _ = vote_scene(num_objects=1, per_object=50, num_background=10)
    del params["vote_offsets"], params["vote_support"]
    return params


@pytest.mark.parametrize(
    "make, kwargs, message",
    [
        (splatfacto_params, {}, "not trained with the votesplat method"),
        (
            lambda: dict(vote_scene()[0], vote_support=torch.zeros(1260, 2)),
            {},
            "no foreground Gaussians at vote level 'instance'",
        ),
        (lambda: vote_scene()[0], {"clustering": ClusteringOptions(min_cluster_size=5000)}, "was labelled noise"),
        (lambda: vote_scene()[0], {"remove": [9]}, r"cannot remove instances \[9\]"),
        (lambda: vote_scene()[0], {"level": "object"}, "unknown vote level 'object'"),
        (lambda: vote_scene()[0], {"level_names": ("instance",)}, "2 vote levels but 1 level names"),
        (lambda: 3, {}, "expected a VoteSplat model"),
    ],
)
def test_bad_input_is_a_clear_error_and_writes_nothing(tmp_path, make, kwargs, message):
    with pytest.raises(ValueError, match=message):
        export(make(), tmp_path / "out", **kwargs)
    assert no_leftovers(tmp_path)


def test_output_dir_that_is_a_file_or_a_foreign_folder(tmp_path):
    params, _ = vote_scene()
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="is a file"):
        export(params, tmp_path / "file")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    with pytest.raises(ValueError, match="not a previous instance export"):
        export(params, tmp_path / "mine")
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep me"
    (tmp_path / "empty").mkdir()
    export(params, tmp_path / "empty")
    assert (tmp_path / "empty" / "instances.json").is_file()


def test_a_previous_export_is_replaced_only_without_user_files(tmp_path, monkeypatch):
    params, _ = vote_scene()
    out = tmp_path / "out"
    export(params, out, remove=[1])
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    (out / "NOTES.txt").write_text("the mug is instance 2")
    with pytest.raises(
        ValueError, match=rf"^output_dir {out} holds NOTES.txt, which an instance export does not write"
    ):
        export(params, out)
    (out / "instances" / "mine").mkdir()
    with pytest.raises(ValueError, match=r"holds NOTES.txt \(and 1 more\)"):
        export(params, out)
    assert (out / "NOTES.txt").read_text() == "the mug is instance 2"
    assert {
        p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file() and p.name != "NOTES.txt"
    } == before
    (out / "NOTES.txt").unlink()
    (out / "instances" / "mine").rmdir()

    # a previous export whose folders this process may not write could not be deleted once replaced
    real_access = os.access
    monkeypatch.setattr(
        instance_export_module.os,
        "access",
        lambda path, mode: Path(path) != out / "instances" and real_access(path, mode),
    )
    with pytest.raises(ValueError, match=rf"the previous export's folder {out / 'instances'} is not writable"):
        export(params, out)
    monkeypatch.setattr(instance_export_module.os, "access", real_access)
    assert no_leftovers(tmp_path, keep=["out"])
    export(params, out)  # replaces it: scene_without_1.ply is gone, nothing hidden is left beside it
    assert not (out / "scene_without_1.ply").exists() and no_leftovers(tmp_path, keep=["out"])


def test_an_old_export_that_cannot_be_deleted_is_reported(tmp_path, monkeypatch):
    params, _ = vote_scene()
    export(params, tmp_path / "out")

    def refuse(path, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(instance_export_module.shutil, "rmtree", refuse)
    with pytest.warns(
        UserWarning, match=r"could not be deleted .*Permission denied.*; delete .*\.out\.old\..* yourself"
    ):
        export(params, tmp_path / "out")


def test_non_finite_votes_are_counted(tmp_path):
    params, object_of = vote_scene()
    params["vote_offsets"][:5, 0] = float("nan")  # supported foreground Gaussians
    params["means"][10, 2] = float("inf")
    params["vote_offsets"][-1, 1] = float("nan")  # background (no support): not counted
    manifest = export(params, tmp_path / "out")
    assert manifest["export"]["nonfinite_votes"] == {"instance": 6, "part": 1}
    instance_level = InstanceSet.load(tmp_path / "out").levels[0]
    assert (instance_level.ids[:5] == -1).all() and not instance_level.foreground[:5].any()  # background, as reported


def test_viewmat_matches_splatfacto():
    from nerfstudio.models.splatfacto import get_viewmat

    rng = np.random.default_rng(0)
    rotation, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    c2w = torch.tensor(np.concatenate([rotation, rng.normal(size=(3, 1))], axis=1), dtype=torch.float32)
    splatfacto_viewmat = get_viewmat.__wrapped__  # the function under torch.compile's wrapper
    torch.testing.assert_close(viewmat_from_camera_to_world(c2w), splatfacto_viewmat(c2w[None])[0])
    opencv_c2w = torch.eye(4)
    opencv_c2w[:3] = c2w * torch.tensor([1.0, -1.0, -1.0, 1.0])
    torch.testing.assert_close(viewmat_from_camera_to_world(c2w), torch.linalg.inv(opencv_c2w), atol=1e-5, rtol=1e-5)


def stub_pipeline(model, width=40, height=30, views=3):
    from nerfstudio.cameras.cameras import Cameras, CameraType

    c2w = torch.zeros(views, 3, 4)
    c2w[:, :3, :3] = torch.eye(3)
    c2w[:, :, 3] = torch.tensor(
        [[x, 0.0, 8.0] for x in np.linspace(-0.5, 0.5, views)]
    )  # looking down -z at the objects
    cameras = Cameras(
        camera_to_worlds=c2w,
        fx=24.0,
        fy=24.0,
        cx=width / 2,
        cy=height / 2,
        width=width,
        height=height,
        camera_type=CameraType.PERSPECTIVE,
    )

    class Dataset:
        def __init__(self):
            self.cameras = cameras

        def __getitem__(self, index):
            return {"image": torch.full((height, width, 3), 0.5)}

    return SimpleNamespace(model=model, datamanager=SimpleNamespace(train_dataset=Dataset()))


def test_cli_main_with_a_loaded_pipeline(tmp_path, monkeypatch):
    params, _ = vote_scene(num_background=0)
    model = SimpleNamespace(gauss_params=params, config=SimpleNamespace(vote_levels=LEVELS, sh_degree=3))
    monkeypatch.setattr(
        export_module, "load_run", lambda *a, **k: LoadedRun(stub_pipeline(model), TrainedScene.from_model(model), 0)
    )
    command = ExportVoteSplatInstances(
        load_config=tmp_path / "config.yml",
        output_dir=tmp_path / "out",
        level="part",
        remove=(2,),
        num_views=2,
        picture_width=20,
    )
    command.main()
    manifest = json.loads((tmp_path / "out" / "instances.json").read_text())
    assert manifest["export"]["level"] == "part" and manifest["export"]["removed"]["ids"] == [2]
    assert manifest["export"]["source"] == str(tmp_path / "config.yml")
    assert manifest["export"]["picture"] == "instances.png"  # drawn with the plugin's CPU rasteriser
    from PIL import Image

    picture = np.asarray(Image.open(tmp_path / "out" / "instances.png"))
    assert picture.shape == (15 * 2 + 4, 20 * 2 + 4, 3)  # photos above id maps, 2 views at 20 px width
    assert (picture[:15, :20] == 128).all()  # the (grey) training photo
    colours = {tuple(i["color"]) for i in manifest["levels"][1]["instances"]}
    assert len(colours & {tuple(c) for c in picture[19:, :20].reshape(-1, 3)}) >= 4  # parts drawn in their colours


def test_cli_main_reports_bad_input_in_one_line(tmp_path, monkeypatch, capsys):
    model = SimpleNamespace(gauss_params=splatfacto_params(), config=SimpleNamespace(sh_degree=3))
    monkeypatch.setattr(
        export_module, "load_run", lambda *a, **k: LoadedRun(stub_pipeline(model), TrainedScene.from_model(model), 0)
    )
    monkeypatch.setattr(sys, "argv", ["/venv/bin/ns-export", SUBCOMMAND_NAME, "--load-config", "c.yml"])
    with pytest.raises(SystemExit) as exit_info:
        ExportVoteSplatInstances(load_config=tmp_path / "c.yml", output_dir=tmp_path / "out", num_views=0).main()
    assert exit_info.value.code == 1
    error = capsys.readouterr().err
    assert (
        error.startswith("ns-export votesplat-instances: error: the checkpoint has no vote_offsets")
        and error.count("\n") == 1
    )
    assert "not trained with the votesplat method" in error
    assert not (tmp_path / "out").exists()


FAKE_EXPORTER = """
from dataclasses import dataclass
from typing import Union

import tyro
from typing_extensions import Annotated

{hook}

@dataclass
class Other:
    x: int = 1

    def main(self):
        return self.x


Commands = tyro.conf.FlagConversionOff[
    Union[Annotated[Other, tyro.conf.subcommand(name="other")], Annotated[Other, tyro.conf.subcommand(name="again")]]
]


def entrypoint(args):
    return tyro.cli(Commands, args=args)
"""


def subcommands(commands):
    union = typing.get_args(commands)[0]
    return [typing.get_args(member)[0] for member in typing.get_args(union)]


@pytest.mark.parametrize("case", ["during_import", "before_import", "after_import"])
def test_hook_extends_the_exporter_commands(tmp_path, monkeypatch, case):
    name = f"fake_exporter_{case}"
    hook = (
        f"import votesplat_ns.ns.patches\nvotesplat_ns.ns.patches.install_ns_export_hook({name!r})"
        if case == "during_import"
        else ""
    )
    (tmp_path / f"{name}.py").write_text(textwrap.dedent(FAKE_EXPORTER.format(hook=hook)))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(sys, "meta_path", list(sys.meta_path))
    try:
        if case == "before_import":
            install_ns_export_hook(name)
        module = importlib.import_module(name)
        if case == "after_import":
            install_ns_export_hook(name)
        entrypoint = module.entrypoint  # the console script's "from exporter import entrypoint"
        install_ns_export_hook(name)  # idempotent
        assert type(module) is type(sys)
        assert [cls.__name__ for cls in subcommands(module.Commands)] == ["Other", "Other", "ExportVoteSplatInstances"]
        parsed = entrypoint([SUBCOMMAND_NAME, "--load-config", "c.yml", "--output-dir", "o", "--remove", "1", "2"])
        assert (
            isinstance(parsed, ExportVoteSplatInstances) and parsed.remove == (1, 2) and parsed.output_dir == Path("o")
        )
        assert entrypoint(["other", "--x", "3"]).main() == 3
    finally:
        sys.modules.pop(name, None)


def console_script(name):
    path = Path(sys.executable).parent / name
    return str(path) if path.exists() else shutil.which(name)


def test_ns_export_lists_the_votesplat_subcommand(run_console_script):
    ns_export = console_script("ns-export")
    assert ns_export, "ns-export is not installed next to this Python"
    result = run_console_script([ns_export, SUBCOMMAND_NAME, "--help"])
    assert result.returncode == 0, result.stderr[-2000:]
    for option in (
        "--load-config",
        "--output-dir",
        "--level",
        "--remove",
        "--min-cluster-size",
        "--min-samples",
        "--max-points",
        "--noise",
        "--num-views",
    ):
        assert option in result.stdout, option


def test_votesplat_export_console_script(run_console_script):
    script = console_script("votesplat")
    assert script, "votesplat is not installed (pip install -e .)"
    result = run_console_script([script, "export", "--help"])
    assert result.returncode == 0, result.stderr[-2000:]
    assert "--load-config" in result.stdout and "--remove" in result.stdout


def test_the_export_commands_clustering_flags_reach_cluster_levels():
    flags = dict(
        min_cluster_size=7,
        min_samples=2,
        max_points=100,
        noise="drop",
        noise_radius=0.1,
        cluster_selection_epsilon=0.2,
        seed=3,
    )
    command = ExportVoteSplatInstances(load_config=Path("config.yml"), output_dir=Path("out"), **flags)
    assert command.clustering() == ClusteringOptions(**flags)
    assert command.clustering().kwargs() == dict(flags, coarse_to_fine=True)
