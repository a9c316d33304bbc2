"""Bad-input catalogue: the real commands, in subprocesses, given what a clumsy user gives them.

Every case runs one console script (ns-train votesplat, ns-export votesplat-instances, votesplat
query/click/masks) in a workspace of its own and checks
  - the exit code,
  - for a failure: one line ``<command>: error: ...`` naming the file or flag, and no traceback,
  - for a run that must go on: its warning, said once,
  - the workspace afterwards: every file that was there is unchanged, and new paths are only those
    the case allows (no partial or hidden temporary files, user files untouched).
ns-train writes its run's config.yml before the plugin runs (nerfstudio's order), so ns-train
cases allow that one file. Cases that need a folder the command may not write make it read-only;
when the tests run as root (who may write anywhere) the command runs without the capabilities
that let root ignore file permissions (setpriv).

Most cases fail before training or loading starts, so each costs about the command's start-up.
The cases that need a trained run copy the session's ``trained_demo`` (tests/conftest.py).

Issue 16, items 3-7 (item 8, the help, is checked in test_method.py):
  3 masks_without_any_vote, vote_start_after_the_last_step
  4 truncated_training_image, nan_in_a_pose, read_only_cache_folder, truncated_checkpoint, read_only_export_target
  5 damaged_cache_entry
  6 some_frames_without_instance_masks, hidden_folder_in_the_mask_folder, image_of_the_wrong_size,
    garbage_clip_checkpoint, duplicate_frames, query_longer_than_clip_reads
  7 export_over_a_user_file, previous_export_that_cannot_be_deleted, non_finite_vote_offsets
Issue 37 (SAM masks): sam_checkpoint_of_another_model_type, truncated_sam_checkpoint,
  sixteen_bit_grey_image_for_sam (grey and RGBA images are read as RGB: tests/test_data_checks.py).
The other cases are earlier ones (issue 2) and neighbours of these.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np
import pytest
import torch
from PIL import Image

DEMO_SCENE = Path(__file__).resolve().parents[1] / "votesplat_ns" / "data" / "demo"
BIN = Path(sys.executable).parent
# root ignores file permissions through these capabilities; without them a read-only folder is read-only
DROP_ROOT_OVERRIDES = (
    ["setpriv", "--bounding-set", "-dac_override,-dac_read_search,-fowner", "--"] if os.geteuid() == 0 else []
)
TEMP_MARKERS = (".tmp-", ".partial.", ".old.")


# ------------------------------------------------------------------ workspace
class Workspace:
    """A folder for one case."""

    def __init__(self, root: Path):
        self.root = root
        self.drop_root_overrides = False
        self._locked: List[Path] = []
        self.home = root / "home"
        self.home.mkdir()

    def read_only(self, path: Path) -> Path:
        """Make ``path`` (a folder) read-only for the command."""
        if os.geteuid() == 0 and shutil.which("setpriv") is None:
            pytest.skip("running as root without setpriv: a read-only folder cannot be made here")
        path.mkdir(parents=True, exist_ok=True)
        path.chmod(0o555)
        self._locked.append(path)
        self.drop_root_overrides = bool(DROP_ROOT_OVERRIDES)
        return path

    def unlock(self) -> None:
        for path in self._locked:
            path.chmod(0o755)

    def scene(self, name: str = "scene") -> Path:
        """A copy of the bundled demo dataset."""
        target = self.root / name
        shutil.copytree(DEMO_SCENE, target, ignore=shutil.ignore_patterns("README.md"))
        return target


def edit_transforms(scene: Path, edit: Callable[[dict], None]) -> None:
    path = scene / "transforms.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta, indent=2))


def truncate(path: Path, keep: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def copy_run(config_path: Path, output_dir: Path) -> Path:
    """A copy of a trained run under ``output_dir``; returns its config.yml (which points at the copy)."""
    import yaml

    config = yaml.load(Path(config_path).read_text(), Loader=yaml.Loader)
    config.output_dir = output_dir
    # without the instances another command kept beside the original (ns/run_instances.py): each case starts clean
    shutil.copytree(
        Path(config_path).parent, config.get_base_dir(), ignore=shutil.ignore_patterns("votesplat_instances")
    )
    (config.get_base_dir() / "config.yml").write_text(yaml.dump(config))
    return config.get_base_dir() / "config.yml"


def checkpoint_of(config_path: Path) -> Path:
    return sorted((config_path.parent / "nerfstudio_models").glob("step-*.ckpt"))[-1]


def snapshot(root: Path) -> Dict[str, str]:
    """Every path under ``root`` (but home/) and, for files, a digest of the bytes."""
    state = {}
    for folder, dirs, files in os.walk(root):
        for name in dirs:
            state[os.path.relpath(os.path.join(folder, name), root)] = "dir"
        for name in files:
            path = os.path.join(folder, name)
            with open(path, "rb") as handle:
                state[os.path.relpath(path, root)] = hashlib.sha256(handle.read()).hexdigest()
    return {path: value for path, value in state.items() if path != "home" and not path.startswith("home/")}


# ------------------------------------------------------------------ cases
@dataclass
class Expect:
    argv: List[str]
    exit_code: int = 1
    needles: Sequence[str] = ()
    """Failure: substrings of the error line. Success: substrings the output must hold exactly once."""
    forbidden: Sequence[str] = ()
    """Substrings the output must not hold (besides 'Traceback')."""
    new_paths: Sequence[str] = ()
    """Globs (relative to the workspace) of paths the command may create."""
    changed_paths: Sequence[str] = ()
    """Globs of existing files the command may change."""
    after: Optional[Callable[[], None]] = None
    """More checks once the command has run."""


# One training step that votes, without the end-of-training foreground pass (it renders every view).
ONE_VOTE_STEP = ("--pipeline.model.vote-start-step", "0", "--pipeline.model.foreground-min-masked-share", "None")
NS_TRAIN_RUN_FILES = ("runs", "runs/*", "runs/*/votesplat", "runs/*/votesplat/*", "runs/*/votesplat/*/config.yml")


def ns_train(ws: Workspace, data: Path, *extra: str, cache: Optional[Path] = None) -> List[str]:
    runs = ws.root / "runs"
    return [
        str(BIN / "ns-train"),
        "votesplat",
        "--data",
        str(data),
        "--vis",
        "tensorboard",
        "--max-num-iterations",
        "1",
        "--output-dir",
        str(runs),
        "--machine.device-type",
        "cpu",
        "--pipeline.datamanager.cache-dir",
        str(cache or ws.root / "cache"),
        *extra,
    ]


def ns_export(config: Path, output_dir: Path, *extra: str) -> List[str]:
    return [
        str(BIN / "ns-export"),
        "votesplat-instances",
        "--load-config",
        str(config),
        "--output-dir",
        str(output_dir),
        "--num-views",
        "0",
        *extra,
    ]


def masks(data: Path, *extra: str) -> List[str]:
    return [str(BIN / "votesplat"), "masks", "--data", str(data), *extra]


CASES: Dict[str, Callable[..., Expect]] = {}


def case(function: Callable[..., Expect]) -> Callable[..., Expect]:
    CASES[function.__name__] = function
    return function


# ---- the dataset: found before anything is trained or cached (datamanager.check_data_input)
@case
def missing_data_folder(ws, fixtures):
    missing = ws.root / "nonexistent"
    return Expect(
        ns_train(ws, missing),
        needles=[f"--data {missing}: folder not found", "ns-process-data"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def folder_without_transforms_json(ws, fixtures):
    photos = ws.root / "photos"
    photos.mkdir()
    (photos / "IMG_0001.jpg").write_bytes(b"not really a photo")
    return Expect(
        ns_train(ws, photos),
        needles=["this folder holds no transforms.json", "ns-process-data"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def images_missing(ws, fixtures):
    scene = ws.scene()
    shutil.rmtree(scene / "images")
    return Expect(
        ns_train(ws, scene),
        needles=[
            "34 of 34 images listed in transforms.json are missing",
            f"(first: {scene / 'images' / 'frame_00001.png'})",
        ],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def cuda_requested_without_cuda(ws, fixtures):
    if torch.cuda.is_available():
        pytest.skip("CUDA is available here, so --machine.device-type cuda is valid input")
    argv = ns_train(ws, DEMO_SCENE, "--machine.device-type", "cuda")
    return Expect(
        argv,
        needles=["CUDA is not available on this machine", "--machine.device-type cpu"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def truncated_training_image(ws, fixtures):
    scene = ws.scene()
    truncate(scene / "images" / "frame_00003.png")
    # found while the masks are made: the views before it are complete cache entries, kept for the next run
    return Expect(
        ns_train(ws, scene),
        needles=[f"image {scene / 'images' / 'frame_00003.png'} cannot be read", "truncated", "replace it"],
        new_paths=NS_TRAIN_RUN_FILES + ("cache", "cache/*", "cache/*/*"),
    )


@case
def nan_in_a_pose(ws, fixtures):
    scene = ws.scene()
    edit_transforms(scene, lambda meta: meta["frames"][7]["transform_matrix"][0].__setitem__(3, float("nan")))
    return Expect(
        ns_train(ws, scene),
        needles=[
            str(scene / "transforms.json"),
            "frame 7 (images/frame_00008.png)",
            "finite numbers",
            "fix or remove that frame",
        ],
        forbidden=["Input X contains NaN"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def pose_that_is_not_a_matrix(ws, fixtures):
    scene = ws.scene()
    edit_transforms(
        scene, lambda meta: meta["frames"][2].__setitem__("transform_matrix", [[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    )
    return Expect(
        ns_train(ws, scene), needles=["frame 2 (images/frame_00003.png)", "4x4 (or 3x4)"], new_paths=NS_TRAIN_RUN_FILES
    )


@case
def nan_focal_length(ws, fixtures):
    scene = ws.scene()
    edit_transforms(scene, lambda meta: meta.__setitem__("fl_x", float("nan")))
    return Expect(
        ns_train(ws, scene),
        needles=["transforms.json: the file has camera value fl_x=nan", "finite number > 0"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def duplicate_frames(ws, fixtures):
    scene = ws.scene()
    edit_transforms(scene, lambda meta: meta["frames"].append(dict(meta["frames"][2])))
    return Expect(
        ns_train(ws, scene),
        needles=["frames 2 and 34 both list images/frame_00003.png", "remove the duplicate"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def some_frames_without_instance_masks(ws, fixtures):
    scene = ws.scene()

    def drop(meta):
        for number in (3, 9):
            del meta["frames"][number]["instance_mask_path"]

    edit_transforms(scene, drop)
    return Expect(
        ns_train(ws, scene),
        needles=[
            "2 of 34 frames list no instance_mask_path",
            "(first: frame 3 (images/frame_00004.png))",
            "--pipeline.datamanager.mask-source sam",
        ],
        forbidden=["SAM checkpoint"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def image_of_the_wrong_size(ws, fixtures):
    scene = ws.scene()
    image = scene / "images" / "frame_00005.png"
    Image.open(image).convert("RGB").resize((100, 80)).save(image)
    return Expect(
        ns_train(ws, scene),
        needles=[f"image {image} is 100x80", "camera (frame 4 (images/frame_00005.png)) as 128x128"],
        forbidden=["label image"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def truncated_label_image(ws, fixtures):
    scene = ws.scene()
    truncate(scene / "instances" / "frame_00002.png")
    return Expect(
        masks(scene, "--cache-dir", str(ws.root / "cache")),
        needles=[f"label image {scene / 'instances' / 'frame_00002.png'} cannot be read", "truncated"],
        new_paths=("cache", "cache/*", "cache/*/*"),
    )


# ---- training that would run to the end for nothing
@case
def vote_start_after_the_last_step(ws, fixtures):
    scene = ws.scene()
    argv = ns_train(ws, scene, "--pipeline.model.vote-start-step", "5", "--max-num-iterations", "3")
    # fails once the step range is known (after the masks are made; they stay cached for the next run)
    return Expect(
        argv,
        needles=[
            "--pipeline.model.vote-start-step 5 is past the last training step 2",
            "--max-num-iterations 3",
            "never run",
        ],
        new_paths=NS_TRAIN_RUN_FILES + ("runs/*/votesplat/*/*", "cache", "cache/*", "cache/*/*"),
    )


@case
def masks_without_any_vote(ws, fixtures):
    scene = ws.scene()
    for folder in ("instances", "parts"):
        for path in (scene / folder).glob("*.png"):
            Image.fromarray(np.zeros((128, 128), np.uint16)).save(path)
    argv = ns_train(ws, scene, *ONE_VOTE_STEP)
    return Expect(
        argv,
        exit_code=0,
        needles=["no mask of the 30 training views gives a vote", "votesplat masks --data"],
        new_paths=("runs", "runs/**", "cache", "cache/**"),
    )


# ---- the vote cache
@case
def read_only_cache_folder(ws, fixtures):
    scene = ws.scene()
    cache = ws.read_only(ws.root / "cache")
    return Expect(
        ns_train(ws, scene, cache=cache),
        needles=[
            f"--pipeline.datamanager.cache-dir {cache}: cannot write",
            "make it writable or choose another --pipeline.datamanager.cache-dir",
        ],
        forbidden=["PermissionError"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def read_only_cache_folder_of_votesplat_masks(ws, fixtures):
    scene = ws.scene()
    cache = ws.read_only(ws.root / "cache")
    return Expect(
        masks(scene, "--cache-dir", str(cache)),
        needles=[f"--cache-dir {cache}: cannot write", "choose another --cache-dir"],
    )


@case
def damaged_cache_entry(ws, fixtures):
    from votesplat_ns.cli.masks_cli import MasksConfig, main as make_masks

    scene = ws.scene()
    cache = ws.root / "cache"
    made = make_masks(MasksConfig(data=scene, cache_dir=cache))
    key = made["keys"][0]
    labels_path = made["entry_dir"] / f"{key}.labels.npy"
    original = labels_path.read_bytes()
    with np.load(made["entry_dir"] / f"{key}.votes.npz") as record:
        masks_at_level_0 = record["centroids_0"].shape[0] - 1
    labels = np.load(labels_path)
    labels[0, 0, 0] = masks_at_level_0 + 5  # same shape and dtype, an id past the centroid table
    np.save(labels_path, labels)

    def rebuilt_identical():
        assert labels_path.read_bytes() == original

    argv = ns_train(ws, scene, *ONE_VOTE_STEP, cache=cache)
    return Expect(
        argv,
        exit_code=0,
        needles=[f"vote cache entry {key}.votes.npz", "is damaged", "rebuilding it"],
        forbidden=["IndexError"],
        new_paths=("runs", "runs/**"),
        changed_paths=("cache/*/*",),
        after=rebuilt_identical,
    )


# ---- masks
@case
def hidden_folder_in_the_mask_folder(ws, fixtures):
    scene = ws.scene()
    mask_folder = ws.root / "masks"
    shutil.copytree(scene / "instances", mask_folder / "instance")
    shutil.copytree(scene / "parts", mask_folder / "part")
    shutil.copytree(scene / "parts", mask_folder / ".ipynb_checkpoints")
    argv = masks(scene, "--source", "folder", "--mask-folder", str(mask_folder), "--cache-dir", str(ws.root / "cache"))
    return Expect(argv, exit_code=0, needles=["levels ['instance', 'part']"], new_paths=("cache", "cache/**"))


@case
def more_mask_processes_than_gpus(ws, fixtures):
    scene = ws.scene()
    too_many = max(2, torch.cuda.device_count() + 1)
    argv = masks(scene, "--num-gpus", str(too_many), "--cache-dir", str(ws.root / "cache"))
    return Expect(argv, needles=[f"--num-gpus {too_many}: this machine has", "--sam-device cpu"])


@case
def read_only_cache_folder_of_votesplat_masks_on_two_processes(ws, fixtures):
    scene = ws.scene()
    cache = ws.read_only(ws.root / "cache")
    return Expect(
        masks(scene, "--cache-dir", str(cache), "--num-gpus", "2", "--sam-device", "cpu"),
        needles=[f"--cache-dir {cache}: cannot write", "choose another --cache-dir"],
    )


@case
def garbage_sam_checkpoint(ws, fixtures):
    scene = ws.scene()
    checkpoint = ws.root / "sam_vit_b_01ec64.pth"
    checkpoint.write_bytes(b"<html>404 Not Found</html>" * 40)
    argv = masks(
        scene,
        "--source",
        "sam",
        "--sam-checkpoint",
        str(checkpoint),
        "--sam-model-type",
        "vit_b",
        "--sam-device",
        "cpu",
        "--cache-dir",
        str(ws.root / "cache"),
    )
    return Expect(
        argv,
        needles=[f"could not load SAM checkpoint {checkpoint}", "not a PyTorch weights file"],
        forbidden=["weights_only"],
    )


def sam_masks(ws: Workspace, scene: Path, checkpoint: Path, model_type: str = "vit_b") -> List[str]:
    return masks(
        scene,
        "--source",
        "sam",
        "--sam-checkpoint",
        str(checkpoint),
        "--sam-model-type",
        model_type,
        "--sam-device",
        "cpu",
        "--cache-dir",
        str(ws.root / "cache"),
    )


@case
def sam_checkpoint_of_another_model_type(ws, fixtures):
    scene = ws.scene()
    checkpoint = ws.root / "sam_vit_l_0b3195.pth"
    torch.save({"image_encoder.patch_embed.proj.weight": torch.zeros(1024, 3, 16, 16)}, checkpoint)  # vit_l's width
    return Expect(
        sam_masks(ws, scene, checkpoint, "vit_b"),
        needles=[f"could not load SAM checkpoint {checkpoint} as model type 'vit_b'", "weights of another model"],
        forbidden=["weights_only"],
    )


@case
def truncated_sam_checkpoint(ws, fixtures):
    scene = ws.scene()
    checkpoint = ws.root / "sam_vit_b_01ec64.pth"
    torch.save({"image_encoder.patch_embed.proj.weight": torch.zeros(768, 3, 16, 16)}, checkpoint)
    truncate(checkpoint)
    return Expect(
        sam_masks(ws, scene, checkpoint),
        needles=[f"could not load SAM checkpoint {checkpoint} as model type 'vit_b'", "truncated"],
        forbidden=["weights_only"],
    )


@case
def sixteen_bit_grey_image_for_sam(ws, fixtures):
    scene = ws.scene()
    image = scene / "images" / "frame_00005.png"
    grey = np.asarray(Image.open(image).convert("L")).astype(np.uint16) * 257
    Image.fromarray(grey).save(image)
    checkpoint = ws.root / "sam_vit_b_01ec64.pth"
    checkpoint.write_bytes(b"never read")
    return Expect(
        sam_masks(ws, scene, checkpoint),
        needles=[f"image {image} is a 16/32-bit single-channel image (PIL mode I;16)", "8-bit RGB or greyscale"],
    )


# ---- export
@case
def truncated_checkpoint(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    checkpoint = checkpoint_of(config)
    truncate(checkpoint)
    return Expect(ns_export(config, ws.root / "export"), needles=[f"checkpoint {checkpoint}", "truncated or damaged"])


@case
def run_without_checkpoint(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    shutil.rmtree(config.parent / "nerfstudio_models")
    return Expect(ns_export(config, ws.root / "export"), needles=[f"--load-config {config}: the run has no checkpoint"])


@case
def read_only_export_target(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    shared = ws.read_only(ws.root / "shared")
    target = shared / "export"
    return Expect(
        ns_export(config, target),
        needles=[f"--output-dir {target}: cannot write in {shared}", "choose another --output-dir"],
    )


@case
def export_target_is_a_file(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    target = ws.root / "export.ply"
    target.write_text("mine")
    return Expect(ns_export(config, target), needles=[f"--output-dir {target} is a file"])


@case
def export_over_a_user_file(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    target = ws.root / "export"
    shutil.copytree(fixtures.previous_export, target)
    (target / "NOTES.txt").write_text("which object is which")
    return Expect(
        ns_export(config, target),
        needles=[f"--output-dir {target} holds NOTES.txt", "would delete it", "move it out of that folder"],
    )


@case
def previous_export_that_cannot_be_deleted(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    target = ws.root / "exports" / "export"
    shutil.copytree(fixtures.previous_export, target)
    ws.read_only(target / "instances")
    return Expect(
        ns_export(config, target), needles=[f"the previous export's folder {target / 'instances'} is not writable"]
    )


@case
def non_finite_vote_offsets(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    checkpoint = checkpoint_of(config)
    state = torch.load(checkpoint, map_location="cpu", weights_only=False)
    pipeline = state["pipeline"]
    supported = torch.nonzero(pipeline["_model.gauss_params.vote_support"][:, 0] > 0).squeeze(1)[:7]
    pipeline["_model.gauss_params.vote_offsets"][supported, 0] = float("nan")
    torch.save(state, checkpoint)
    target = ws.root / "export"
    return Expect(
        ns_export(config, target),
        exit_code=0,
        needles=[
            "Warning: 7 Gaussians with vote support at level 'instance' have a NaN/Inf mean or vote offset",
            "exported as background",
        ],
        # the run's instances are kept beside it (ns/run_instances.py)
        new_paths=("export", "export/**", "run/*/*/*/votesplat_instances", "run/*/*/*/votesplat_instances/**"),
    )


# ---- query and click
def votesplat(command: str, config: Path, *extra: str) -> List[str]:
    return [str(BIN / "votesplat"), command, "--load-config", str(config), *extra]


@case
def missing_run_config(ws, fixtures):
    missing = ws.root / "outputs" / "config.yml"
    argv = votesplat("query", missing, "mug", "--clip-random-init", "--clip-model", "ViT-S-32-alt")
    return Expect(argv, needles=[f"--load-config {missing}: file not found"])


@case
def garbage_clip_checkpoint(ws, fixtures):
    weights = ws.root / "open_clip_pytorch_model.bin"
    weights.write_bytes(b"Entry not found" * 100)
    argv = votesplat("query", fixtures.trained_demo, "red mug", "--clip-checkpoint", str(weights))
    return Expect(
        argv,
        needles=[f"{weights} does not hold open_clip weights for 'ViT-B-16'", "not a PyTorch weights file"],
        forbidden=["weights_only"],
    )


@case
def query_longer_than_clip_reads(ws, fixtures):
    text = "a red mug on the table next to the lamp " * 225  # 9000 characters
    argv = votesplat("query", fixtures.trained_demo, text, "--clip-random-init", "--clip-model", "ViT-S-32-alt")
    return Expect(argv, needles=["(9000 characters) is", "tokens long, but CLIP reads at most 75", "shorten it"])


@case
def click_into_a_read_only_folder(ws, fixtures):
    shared = ws.read_only(ws.root / "shared")
    argv = votesplat(
        "click", fixtures.trained_demo, "--view", "0", "--x", "64", "--y", "64", "--output-dir", str(shared / "sel")
    )
    return Expect(argv, needles=[f"--output-dir {shared / 'sel'}: cannot write in {shared}"])


# ------------------------------------------------------------------ running a case
PROGRAMS = {"ns-train": "ns-train votesplat", "ns-export": "ns-export votesplat-instances"}


def program_of(argv: Sequence[str]) -> str:
    name = Path(argv[0]).name
    return PROGRAMS.get(name, f"{name} {argv[1]}")


def run_command(ws: Workspace, argv: Sequence[str]) -> subprocess.CompletedProcess:
    env = dict(
        os.environ,
        COLUMNS="200",
        HOME=str(ws.home),
        XDG_CACHE_HOME=str(ws.home / ".cache"),
        MPLCONFIGDIR=str(ws.home / ".matplotlib"),
    )
    prefix = DROP_ROOT_OVERRIDES if ws.drop_root_overrides else []
    return subprocess.run(
        prefix + list(argv), capture_output=True, check=False, text=True, cwd=ws.home, timeout=900, env=env
    )


def matches(path: str, patterns: Sequence[str]) -> bool:
    """Whether ``path`` matches a glob: ``*`` stays within one folder, a final ``**`` takes everything below."""
    parts = path.split("/")
    for pattern in patterns:
        globs = pattern.split("/")
        if globs[-1] == "**":
            globs = globs[:-1]
            if len(parts) > len(globs) and all(fnmatch.fnmatchcase(p, g) for p, g in zip(parts, globs)):
                return True
        elif len(parts) == len(globs) and all(fnmatch.fnmatchcase(p, g) for p, g in zip(parts, globs)):
            return True
    return False


@dataclass
class Fixtures:
    trained_demo: Path
    previous_export: Path


@pytest.fixture(scope="module")
def fixtures(trained_demo, tmp_path_factory) -> Fixtures:
    """A copy of the trained demo run and an instance export of it (ns-export, as a user would make it)."""
    base = tmp_path_factory.mktemp("bad_inputs")
    config = copy_run(trained_demo, base / "run")
    export = base / "export"
    result = subprocess.run(
        ns_export(config, export),
        capture_output=True,
        check=False,
        text=True,
        timeout=900,
        env=dict(os.environ, COLUMNS="200"),
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return Fixtures(trained_demo=config, previous_export=export)


@pytest.fixture
def workspace(tmp_path):
    ws = Workspace(tmp_path)
    yield ws
    ws.unlock()


@pytest.mark.slow  # every case starts a console script; several train a step or load a trained run
@pytest.mark.parametrize("name", sorted(CASES))
def test_bad_input(name, workspace, fixtures):
    expect = CASES[name](workspace, fixtures)
    before = snapshot(workspace.root)
    result = run_command(workspace, expect.argv)
    output = result.stdout + result.stderr
    assert result.returncode == expect.exit_code, output[-4000:]
    assert "Traceback" not in output, output[-4000:]
    for text in expect.forbidden:
        assert text not in output, output[-4000:]
    if expect.exit_code != 0:
        errors = [line for line in result.stderr.splitlines() if ": error: " in line]
        assert len(errors) == 1, result.stderr[-4000:]
        last = [line for line in result.stderr.splitlines() if line.strip()][-1]
        assert last == errors[0] and last.startswith(f"{program_of(expect.argv)}: error: "), result.stderr[-4000:]
        for needle in expect.needles:
            assert needle in last, last
    else:
        for needle in expect.needles:
            assert output.count(needle) == 1, (needle, output[-4000:])

    workspace.unlock()
    after = snapshot(workspace.root)
    changed = [
        path
        for path in before
        if path in after and after[path] != before[path] and not matches(path, expect.changed_paths)
    ]
    assert not changed, f"{name} changed {changed}"
    assert not [path for path in before if path not in after], f"{name} removed files"
    unexpected = [path for path in after if path not in before and not matches(path, expect.new_paths)]
    assert not unexpected, f"{name} left {unexpected}"
    leftovers = [path for path in after if any(marker in Path(path).name for marker in TEMP_MARKERS)]
    assert not leftovers, f"{name} left temporary files {leftovers}"
    if expect.after is not None:
        expect.after()
