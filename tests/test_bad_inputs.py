"""Bad-input catalogue: the real commands given what a clumsy user (or an attacker) gives them, and the probe
that sums up how every case ended.

Every case runs one console script (ns-train votesplat, ns-export votesplat-instances, ns-viewer, votesplat
export/query/click/query-eval/masks) in a workspace of its own. Most run it in a process of its own, forked
from a runner that has already imported what the script imports (tests/preloaded_runner.py: the same process a
new interpreter would be once its imports are done, without their seconds of start-up); a case whose fault
cannot be made from outside (a full disk, Ctrl-C at a given step) runs the command's main in this process under
a monkeypatched fault (``Expect.call``). Each case is judged (``judge``) into one verdict:
  - ended in one clear line: the exit code expected, one line ``<command>: error: ...`` (``: interrupted: ``
    for Ctrl-C) last on stderr, naming the file or flag, and no traceback;
  - ran on with what it had to say: exit 0, each expected warning said once, the result checked;
  - or what the probe counts as wrong: a traceback, silent wrong (exit 0 where it must fail, a warning
    missing, a wrong result), data lost (a file that was there changed or gone), an unclear message, files
    left behind (new paths the case does not allow, partial or hidden temporary files).
ns-train writes its run's config.yml before the plugin runs (nerfstudio's order), so ns-train
cases allow that one file. Cases that need a folder the command may not write make it read-only;
when the tests run as root (who may write anywhere) the command runs without the capabilities
that let root ignore file permissions (setpriv).

``test_bad_input`` runs every case (``pytest tests/test_bad_inputs.py -m slow``); at the end of the session
conftest.py prints the probe's report: cases tried, how many ended in one clear line or ran on, and the
counts of tracebacks, silent wrong, data lost, unclear messages and files left behind, with each case that
ended wrongly. Most cases fail before training or loading starts, so each costs little more than a fork.
The cases that need a trained run copy the session's ``trained_demo`` (tests/conftest.py).
"""

from __future__ import annotations

import contextlib
import errno
import fnmatch
import hashlib
import io
import json
import os
import shutil
import signal
import sys
import threading
import time
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np
import pytest
import torch
from conftest import BIN, command_env, run_script
from PIL import Image
from preloaded_runner import PreloadedScripts

DEMO_SCENE = Path(__file__).resolve().parents[1] / "votesplat_ns" / "data" / "demo"
# root ignores file permissions through these capabilities (their numbers in linux/capability.h); without them a
# read-only folder is read-only
ROOT_OVERRIDES = {"dac_override": 1, "dac_read_search": 2, "fowner": 3}
DROP_ROOT_OVERRIDES = (
    ["setpriv", "--bounding-set", ",".join(f"-{name}" for name in ROOT_OVERRIDES), "--"] if os.geteuid() == 0 else []
)
TEMP_MARKERS = (".tmp-", ".partial.", ".old.")


# ------------------------------------------------------------------ workspace
class Workspace:
    """A folder for one case."""

    def __init__(self, root: Path, monkeypatch: pytest.MonkeyPatch):
        self.root = root
        self.monkeypatch = monkeypatch
        """For a case run in-process (``Expect.call``): its fault, undone once the command ends."""
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

    def unreadable(self, path: Path) -> Path:
        """Make the file ``path`` unreadable for the command (mode 000)."""
        if os.geteuid() == 0 and shutil.which("setpriv") is None:
            pytest.skip("running as root without setpriv: an unreadable file cannot be made here")
        path.chmod(0o000)
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
            if os.path.islink(path):  # a link's target, which may be a loop or missing
                state[os.path.relpath(path, root)] = f"link to {os.readlink(path)}"
                continue
            try:
                with open(path, "rb") as handle:
                    state[os.path.relpath(path, root)] = hashlib.sha256(handle.read()).hexdigest()
            except PermissionError:  # a file a case made unreadable: its size and time instead
                stat = os.stat(path)
                state[os.path.relpath(path, root)] = f"unreadable {stat.st_size} {stat.st_mtime_ns}"
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
    removed_paths: Sequence[str] = ()
    """Globs of existing paths the command may delete (leftovers of a killed run, never the user's files)."""
    after: Optional[Callable[[], None]] = None
    """More checks once the command has run (an AssertionError there: the command did something wrong)."""
    call: Optional[Callable[[], object]] = None
    """Run the command in this process instead: ``call()`` is its main, run under a fault the case set up
    with ``ws.monkeypatch`` (a full disk, a Ctrl-C); ``argv`` then only names the command."""
    cwd: Optional[Path] = None
    """The folder the command runs in (default: the workspace's home/)."""
    line: str = ": error: "
    """A failure's one line is ``<command><line><message>`` (``: interrupted: `` for Ctrl-C)."""


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


# transforms.json problems nerfstudio's dataparser asserts on (or scales the scene by zero for): (edit, needles)
def _drop_splits(meta: dict) -> None:
    for split in ("train", "val", "test"):
        meta.pop(f"{split}_filenames", None)


def _frame_size_beside_the_files(meta: dict) -> None:
    meta["frames"][3].update(w=100, h=80)


def _one_frame(meta: dict) -> None:
    meta["frames"] = meta["frames"][:1]
    _drop_splits(meta)


def _fewer_frames_than_the_split_lists(meta: dict) -> None:
    meta["frames"] = meta["frames"][:10]


TRANSFORMS_PROBLEMS: Dict[str, tuple] = {
    "no_focal_length": (
        lambda meta: meta.pop("fl_x"),
        ["no fl_x, neither for the whole file nor for frame 0 (images/frame_00001.png)", "34 of 34 frames lack it"],
    ),
    "frame_size_beside_another_file_size": (
        _frame_size_beside_the_files,
        ["frame 3 (images/frame_00004.png) gives w=100 but the file gives w=128", "nerfstudio reads only the file's"],
    ),
    "one_frame": (_one_frame, ["transforms.json lists one frame", "views from several places"]),
    "split_list_naming_missing_frames": (
        _fewer_frames_than_the_split_lists,
        ["train_filenames lists images/frame_00011.png (and 20 more)", "which no frame lists"],
    ),
}


def transforms_problem(problem: str):
    edit, needles = TRANSFORMS_PROBLEMS[problem]

    def make(ws, fixtures):
        scene = ws.scene()
        edit_transforms(scene, edit)
        return Expect(
            ns_train(ws, scene), needles=[str(scene / "transforms.json")] + needles, new_paths=NS_TRAIN_RUN_FILES
        )

    make.__name__ = f"transforms_json_{problem}"
    return make


for _problem in TRANSFORMS_PROBLEMS:
    case(transforms_problem(_problem))


@pytest.mark.parametrize("problem", sorted(TRANSFORMS_PROBLEMS))
def test_transforms_problems_nerfstudio_asserts_on_are_refused_in_one_line(problem, tmp_path):
    """The checks alone (no command): the catalogue runs the same edits through ns-train."""
    from votesplat_ns.errors import VoteSplatInputError
    from votesplat_ns.ns.datamanager import VoteDataManagerConfig, check_data_input

    scene = tmp_path / "scene"
    shutil.copytree(DEMO_SCENE, scene)
    edit, needles = TRANSFORMS_PROBLEMS[problem]
    edit_transforms(scene, edit)
    with pytest.raises(VoteSplatInputError) as caught:
        check_data_input(VoteDataManagerConfig(data=scene))
    assert "\n" not in str(caught.value) and all(needle in str(caught.value) for needle in needles), caught.value


def test_a_frame_repeating_the_files_camera_values_is_accepted(tmp_path):
    from votesplat_ns.ns.datamanager import VoteDataManagerConfig, check_data_input

    scene = tmp_path / "scene"
    shutil.copytree(DEMO_SCENE, scene)
    edit_transforms(scene, lambda meta: meta["frames"][3].update(w=meta["w"], h=meta["h"], fl_x=meta["fl_x"]))
    check_data_input(VoteDataManagerConfig(data=scene))


# ---- inputs that would train silently wrong (data_checks refuses them)
@case
def jpeg_label_image(ws, fixtures):
    scene = ws.scene()
    label = scene / "instances" / "frame_00002.png"
    ids = np.array(Image.open(label))
    Image.fromarray(ids.astype(np.uint8)).save(label, format="JPEG", quality=95)  # a JPEG under the .png name
    return Expect(
        ns_train(ws, scene), needles=[f"label image {label} is a JPEG file", "PNG"], new_paths=NS_TRAIN_RUN_FILES
    )


@case
def cmyk_training_image(ws, fixtures):
    scene = ws.scene()
    image = scene / "images" / "frame_00003.png"
    Image.open(image).convert("CMYK").save(image.with_suffix(".jpg"), format="JPEG", quality=100)
    image.unlink()

    def renamed(meta):
        old, new = "images/frame_00003.png", "images/frame_00003.jpg"
        meta["frames"][2]["file_path"] = new
        for split in ("train", "val", "test"):
            meta[f"{split}_filenames"] = [new if name == old else name for name in meta[f"{split}_filenames"]]

    edit_transforms(scene, renamed)
    return Expect(
        ns_train(ws, scene),
        needles=[f"image {image.with_suffix('.jpg')} has PIL mode CMYK", "convert it to RGB"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def fisheye_camera_without_its_distortion(ws, fixtures):
    scene = ws.scene()
    edit_transforms(scene, lambda meta: meta.update(camera_model="OPENCV_FISHEYE"))  # k1..k4 all 0
    return Expect(
        ns_train(ws, scene),
        needles=["camera_model OPENCV_FISHEYE with k1..k4 all 0", "trained as a pinhole camera"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def camera_model_splatfacto_cannot_render(ws, fixtures):
    scene = ws.scene()
    edit_transforms(scene, lambda meta: meta.update(camera_model="EQUIRECTANGULAR"))
    return Expect(
        ns_train(ws, scene), needles=["camera_model 'EQUIRECTANGULAR' is not supported"], new_paths=NS_TRAIN_RUN_FILES
    )


# ---- files that could run code (harmless payloads: they would only create a marker file)
class Payload:
    """Pickles as a call of os.system that makes ``marker``: what a planted checkpoint would do."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def no_marker(marker: Path) -> Callable[[], None]:
    def check() -> None:
        assert not marker.exists(), "the payload ran"

    return check


@case
def config_yml_that_runs_code(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    marker = ws.root / "ran"
    text = config.read_text()
    config.write_text(
        text.replace("experiment_name: demo", f"experiment_name: !!python/object/apply:os.system ['touch {marker}']")
    )
    return Expect(
        ns_export(config, ws.root / "export"),
        needles=[f"--load-config {config}: refused to load tag !!python/object/apply:os.system", "could run code"],
        after=no_marker(marker),
    )


@case
def retrofit_from_a_checkpoint_that_runs_code(ws, fixtures):
    marker = ws.root / "ran"
    source = ws.root / "step-000000005.ckpt"
    torch.save({"step": 5, "pipeline": Payload(marker)}, source)
    return Expect(
        ns_train(ws, DEMO_SCENE, "--pipeline.model.retrofit-from", str(source)),
        needles=[f"--pipeline.model.retrofit-from {source}", "Python objects besides weights"],
        forbidden=["weights_only"],
        new_paths=("runs", "runs/**", "cache", "cache/**"),  # read once the masks are made
        after=no_marker(marker),
    )


@case
def resume_from_a_checkpoint_that_runs_code(ws, fixtures):
    marker = ws.root / "ran"
    models = ws.root / "models"
    models.mkdir()
    torch.save({"step": 5, "pipeline": Payload(marker)}, models / "step-000000005.ckpt")
    return Expect(
        ns_train(ws, DEMO_SCENE, "--load-dir", str(models)),
        needles=[f"--load-dir {models}", "Python objects besides weights"],
        forbidden=["weights_only"],
        new_paths=("runs", "runs/**", "cache", "cache/**"),  # read once the masks are made
        after=no_marker(marker),
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


@case
def ctrl_c_during_training(ws, fixtures):
    from nerfstudio.scripts.train import entrypoint

    from votesplat_ns.ns.trainer import VoteSplatTrainer

    scene = ws.scene()
    train_iteration = VoteSplatTrainer.train_iteration

    def press_ctrl_c_during_step_2(self, step):
        result = train_iteration(self, step)
        if step == 2:  # the signal arrives while the step ends
            os.kill(os.getpid(), signal.SIGINT)
        return result

    ws.monkeypatch.setattr(VoteSplatTrainer, "train_iteration", press_ctrl_c_during_step_2)
    argv = ns_train(ws, scene, *ONE_VOTE_STEP)
    argv[argv.index("--max-num-iterations") + 1] = "20"

    def the_last_finished_step_is_saved():
        saved = sorted((ws.root / "runs").glob("*/votesplat/*/nerfstudio_models/step-*.ckpt"))
        assert [path.name for path in saved] == ["step-000000002.ckpt"], saved
        state = torch.load(saved[0], map_location="cpu", weights_only=True)
        assert state["step"] == 2 and "_model.gauss_params.vote_offsets" in state["pipeline"]

    return Expect(
        argv,
        call=entrypoint,
        exit_code=130,
        line=": interrupted: ",
        needles=["stopped after step 2; saved", "nerfstudio_models/step-000000002.ckpt", "--load-dir"],
        new_paths=("runs", "runs/**", "cache", "cache/**"),
        after=the_last_finished_step_is_saved,
    )


@case
def ctrl_c_while_the_masks_are_made(ws, fixtures):
    from nerfstudio.scripts.train import entrypoint

    from votesplat_ns.core.vote_cache import VoteCache

    scene = ws.scene()

    def press_ctrl_c(self, *args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)  # Python turns it into KeyboardInterrupt here
        raise AssertionError("SIGINT did not interrupt")

    ws.monkeypatch.setattr(VoteCache, "build_all", press_ctrl_c)
    return Expect(
        ns_train(ws, scene),
        call=entrypoint,
        exit_code=130,
        line=": interrupted: ",
        needles=["stopped while the run was set up", "nothing was saved"],
        new_paths=NS_TRAIN_RUN_FILES,
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


@case
def user_file_in_a_cache_folder_that_is_rebuilt(ws, fixtures):
    from votesplat_ns.cli.masks_cli import MasksConfig, main as make_masks

    scene = ws.scene()
    cache = ws.root / "cache"
    made = make_masks(MasksConfig(data=scene, cache_dir=cache))
    entry_dir = made["entry_dir"]
    config_json = entry_dir / "config.json"
    config_json.write_text(json.dumps({**json.loads(config_json.read_text()), "levels": ["edited"]}))  # tampered
    (entry_dir / "notes.txt").write_text("which view is which")
    return Expect(
        masks(scene, "--cache-dir", str(cache)),
        exit_code=0,
        needles=["was made with other arguments; rebuilding it (kept notes.txt, which the cache does not write)"],
        changed_paths=("cache/*/*.npy", "cache/*/*.npz", "cache/*/config.json"),
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
def more_mask_processes_per_gpu_than_gpus(ws, fixtures):
    scene = ws.scene()
    too_many = torch.cuda.device_count() + 1
    argv = masks(scene, "--num-gpus", str(too_many), "--processes-per-gpu", "2", "--cache-dir", str(ws.root / "cache"))
    return Expect(argv, needles=[f"--num-gpus {too_many} --processes-per-gpu 2: this machine has"])


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
def sam_device_without_cuda(ws, fixtures):
    if torch.cuda.is_available():
        pytest.skip("CUDA is available here, so --sam-device cuda is valid input")
    scene = ws.scene()
    checkpoint = ws.root / "sam_vit_b_01ec64.pth"
    torch.save({}, checkpoint)  # refused before the checkpoint is read
    argv = sam_masks(ws, scene, checkpoint)
    argv[argv.index("--sam-device") + 1] = "cuda"
    return Expect(argv, needles=["SAM device 'cuda': CUDA is not available on this machine", "--sam-device"])


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


# ---- 3DGS PLY files from elsewhere (a retrofit's source)
def write_ascii_ply(path: Path, columns: Dict[str, np.ndarray]) -> None:
    """A PLY in the ASCII format (as some tools write them), every column a float property."""
    count = len(next(iter(columns.values())))
    header = ["ply", "format ascii 1.0", f"element vertex {count}"]
    header += [f"property float {name}" for name in columns] + ["end_header"]
    table = np.stack([np.asarray(column, np.float32) for column in columns.values()], axis=1)
    with open(path, "w", encoding="ascii") as handle:
        handle.write("\n".join(header) + "\n")
        np.savetxt(handle, table, fmt="%.9g")


def with_vote_offsets(columns: Dict[str, np.ndarray]) -> Dict[str, np.ndarray]:
    """The columns plus the official VoteSplat code's per-Gaussian vote offsets."""
    rng = np.random.default_rng(0)
    count = len(next(iter(columns.values())))
    return {**columns, **{f"vote_offset_{i}": rng.normal(size=count).astype(np.float32) for i in range(3)}}


def test_ascii_big_endian_and_votesplat_plys_read_as_the_binary_one(tmp_path):
    from votesplat_ns.core.ply_io import gaussian_property_names, read_3dgs_ply, read_vertex_ply, write_vertex_ply

    rng = np.random.default_rng(1)
    names = gaussian_property_names(15)
    table = rng.normal(size=(50, len(names))).astype(np.float32)
    columns = {name: table[:, index] for index, name in enumerate(names)}
    write_vertex_ply(tmp_path / "binary.ply", columns)
    expected, degree = read_3dgs_ply(tmp_path / "binary.ply")
    write_ascii_ply(tmp_path / "ascii.ply", columns)
    write_vertex_ply(tmp_path / "votesplat.ply", with_vote_offsets(columns))
    big = (tmp_path / "binary.ply").read_bytes()
    body = big.index(b"end_header\n") + len(b"end_header\n")
    swapped = np.frombuffer(big[body:], "<f4").astype(">f4").tobytes()
    (tmp_path / "big.ply").write_bytes(big[:body].replace(b"binary_little_endian", b"binary_big_endian") + swapped)
    for name in ("ascii", "votesplat", "big"):
        arrays, other_degree = read_3dgs_ply(tmp_path / f"{name}.ply")
        assert other_degree == degree == 3
        for key in expected:
            np.testing.assert_allclose(arrays[key], expected[key], rtol=1e-6, err_msg=f"{name} {key}")
    assert read_vertex_ply(tmp_path / "ascii.ply").keys() == columns.keys()


@case
def retrofit_from_an_ascii_votesplat_ply(ws, fixtures):
    from votesplat_ns.core.ply_io import read_vertex_ply

    source = ws.root / "votesplat_point_cloud.ply"  # a trained scene as the official VoteSplat code writes it, in ASCII
    write_ascii_ply(source, with_vote_offsets(read_vertex_ply(fixtures.previous_export / "scene.ply")))
    argv = ns_train(ws, DEMO_SCENE, *ONE_VOTE_STEP, "--pipeline.model.retrofit-from", str(source))
    return Expect(
        argv,
        exit_code=0,
        needles=[f"Note: {source} holds vote offsets (vote_offset_0..2", "they are not read"],
        new_paths=("runs", "runs/**", "cache", "cache/**"),
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
def viewer_on_a_run_without_checkpoint(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    for checkpoint in (config.parent / "nerfstudio_models").glob("*.ckpt"):  # stopped before its first save
        checkpoint.unlink()
    argv = [str(BIN / "ns-viewer"), "--load-config", str(config), "--viewer.websocket-port", "7999"]
    return Expect(argv, needles=[f"--load-config {config}: the run has no checkpoint"], forbidden=["IndexError"])


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
def output_dir_checked_before_the_run(ws, fixtures):
    target = ws.root / "export.ply"
    target.write_text("mine")
    missing = ws.root / "outputs" / "config.yml"  # the run is read after the folder is checked
    return Expect(ns_export(missing, target), needles=[f"--output-dir {target} is a file"])


def edit_run_config(config_path: Path, edit: Callable[[object], None]) -> None:
    """Change a copied run's config.yml (made by copy_run, so trusted) as ns-train would have written it."""
    import yaml

    config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    edit(config)
    config_path.write_text(yaml.dump(config))


@case
def export_into_the_folder_it_runs_in(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    # the default vote cache, outputs/<dataset>/votesplat_cache, lies under the folder the command runs in
    edit_run_config(config, lambda run: setattr(run.pipeline.datamanager, "cache_dir", None))
    target = ws.root / "export"
    shutil.copytree(fixtures.previous_export, target)
    return Expect(
        ns_export(config, Path(".")),
        cwd=target,
        needles=[
            f"--output-dir . is the folder this command runs in ({target})",
            "run the command from another folder",
        ],
    )


def relative_run(ws: Workspace, fixtures: "Fixtures") -> Path:
    """A copy of the trained run as ns-train writes it when run in ws.root/project with ``--data data/demo``
    (``--output-dir`` left at ``outputs``): every path in its config.yml is relative to that folder."""
    project = ws.root / "project"
    config = copy_run(fixtures.trained_demo, project / "outputs")
    shutil.copytree(DEMO_SCENE, project / "data" / "demo", ignore=shutil.ignore_patterns("README.md"))

    def relative(run):
        run.output_dir = Path("outputs")
        run.data = run.pipeline.datamanager.data = Path("data/demo")
        run.pipeline.datamanager.cache_dir = None  # outputs/demo/votesplat_cache in the project

    edit_run_config(config, relative)
    return config


@case
def export_run_from_another_folder(ws, fixtures):
    config = relative_run(ws, fixtures)

    def nothing_written_where_it_ran():
        assert not (ws.home / "outputs").exists(), "the vote cache was made again in the current folder"

    return Expect(
        ns_export(config, ws.root / "export"),
        exit_code=0,
        needles=["Exported"],
        forbidden=["the run has no checkpoint", "the training masks are unavailable"],
        new_paths=(
            "export",
            "export/**",
            "project/outputs/demo/votesplat_cache",  # the run's own vote cache, made where training made it
            "project/outputs/demo/votesplat_cache/**",
            "project/outputs/demo/votesplat/test/votesplat_instances",
            "project/outputs/demo/votesplat/test/votesplat_instances/**",
        ),
        after=nothing_written_where_it_ran,
    )


def test_a_run_is_read_from_its_own_folder_whatever_the_current_folder(tmp_path, monkeypatch):
    """No model is built: the config alone says where the checkpoints, the data and the vote cache are."""
    import yaml

    from votesplat_ns.ns.method import trainer_config_in_process
    from votesplat_ns.ns.run_config import load_run_config

    project = tmp_path / "project"
    shutil.copytree(DEMO_SCENE, project / "data" / "demo", ignore=shutil.ignore_patterns("README.md"))
    config = trainer_config_in_process(Path("data/demo"), Path("outputs"), 10, 5)
    config.pipeline.datamanager.cache_dir = None
    config.set_experiment_name()  # as ns-train's save_config does
    run_dir = project / "outputs" / str(config.experiment_name) / "votesplat" / str(config.timestamp)
    run_dir.mkdir(parents=True)
    (run_dir / "config.yml").write_text(yaml.dump(config))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    loaded = load_run_config(run_dir / "config.yml")
    assert loaded.get_checkpoint_dir() == run_dir / "nerfstudio_models"
    assert loaded.pipeline.datamanager.data == project / "data" / "demo"
    assert loaded.pipeline.datamanager.cache_dir == project / "outputs" / "demo" / "votesplat_cache"
    monkeypatch.chdir(project)  # where it was trained: the relative paths stay as they were written
    loaded = load_run_config(
        Path("outputs") / str(config.experiment_name) / "votesplat" / str(config.timestamp) / "config.yml"
    )
    assert loaded.pipeline.datamanager.data == Path("data/demo") and loaded.pipeline.datamanager.cache_dir is None
    moved = tmp_path / "moved" / "run"  # a run folder copied elsewhere and renamed: its own checkpoints
    shutil.copytree(run_dir, moved)
    assert load_run_config(moved / "config.yml").get_checkpoint_dir() == moved / "nerfstudio_models"


def moved_dataset_run(ws: Workspace, fixtures: "Fixtures") -> Path:
    """A copy of the trained run whose dataset is no longer where its config.yml says."""
    config = copy_run(fixtures.trained_demo, ws.root / "run")

    def moved(run):
        run.data = run.pipeline.datamanager.data = ws.root / "gone" / "demo"

    edit_run_config(config, moved)
    return config


RUN_RECORD = ("run/*/*/*/votesplat_instances", "run/*/*/*/votesplat_instances/**")


@case
def export_without_the_dataset(ws, fixtures):
    config = moved_dataset_run(ws, fixtures)
    gone = ws.root / "gone" / "demo"
    return Expect(
        ns_export(config, ws.root / "export"),
        exit_code=0,
        needles=[
            f"Warning: the training masks are unavailable (the run's dataset {gone} is not there; pass its folder "
            "with --data); using the vote clustering without the mask check"
        ],
        new_paths=("export", "export/**"),  # the unchecked instances are not kept beside the run
    )


@case
def export_without_the_dataset_or_the_mask_check(ws, fixtures):
    config = moved_dataset_run(ws, fixtures)
    return Expect(
        ns_export(config, ws.root / "export", "--mask-check", "False"),
        exit_code=0,
        needles=["Exported"],
        forbidden=["Warning: the training masks", "error:", "Training views unavailable"],
        new_paths=("export", "export/**") + RUN_RECORD,
    )


@case
def click_on_a_run_whose_dataset_moved(ws, fixtures):
    config = moved_dataset_run(ws, fixtures)
    argv = votesplat("click", config, "--view", "0", "--x", "64", "--y", "64", "--output-dir", str(ws.root / "sel"))
    return Expect(
        argv,
        needles=[f"--load-config {config}: the run's dataset {ws.root / 'gone' / 'demo'} is not there", "with --data"],
    )


@case
def click_with_the_moved_dataset_given(ws, fixtures):
    config = moved_dataset_run(ws, fixtures)
    scene = ws.scene("moved_here")
    output = ws.root / "sel"
    argv = votesplat(
        "click", config, "--view", "0", "--x", "64", "--y", "64", "--output-dir", str(output), "--data", str(scene)
    )
    return Expect(
        argv + ["--no-mask-check"],
        exit_code=0,
        needles=["View 0, pixel (64.0, 64.0): instance"],
        new_paths=("sel", "sel/*") + RUN_RECORD,
    )


@case
def data_flag_to_a_missing_folder(ws, fixtures):
    missing = ws.root / "nowhere"
    argv = votesplat("click", fixtures.trained_demo, "--view", "0", "--x", "64", "--y", "64")
    argv += ["--output-dir", str(ws.root / "sel"), "--data", str(missing)]
    return Expect(argv, needles=[f"--data {missing}: folder not found"])


@case
def eval_on_a_run_whose_dataset_moved(ws, fixtures):
    config = moved_dataset_run(ws, fixtures)
    argv = votesplat("eval", config, "--output-dir", str(ws.root / "scores"))
    return Expect(
        argv,
        needles=[
            f"--load-config {config}: the run's dataset {ws.root / 'gone' / 'demo'} is not there",
            "pass its folder with --data",
        ],
        forbidden=["written by votesplat synth"],
    )


@case
def eval_data_flag_to_a_missing_folder(ws, fixtures):
    config = moved_dataset_run(ws, fixtures)
    missing = ws.root / "nowhere"
    argv = votesplat("eval", config, "--output-dir", str(ws.root / "scores"), "--data", str(missing))
    return Expect(argv, needles=[f"--data {missing}: folder not found"])


@case
def leftovers_of_a_killed_export(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    target = ws.root / "export"
    killed = ws.root / ".export.partial.tmp-4242-0123456789ab"  # what kill -9 during an export leaves
    (killed / "instances").mkdir(parents=True)
    (killed / "scene.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\n")
    hour_ago = time.time() - 3600
    for path in (killed / "scene.ply", killed / "instances", killed):
        os.utime(path, (hour_ago, hour_ago))
    running = ws.root / ".export.partial.tmp-4343-0123456789ab"  # an export in progress in another process
    running.mkdir()

    def only_the_old_one_is_swept():
        assert not killed.exists() and running.is_dir()

    return Expect(
        ns_export(config, target, "--mask-check", "False"),
        exit_code=0,
        needles=["Exported"],
        new_paths=("export", "export/**") + RUN_RECORD,
        removed_paths=(".export.partial.tmp-4242-*", ".export.partial.tmp-4242-*/**"),
        after=only_the_old_one_is_swept,
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


# ---- more of what a clumsy user (or an attacker) gives: empty, unreadable or mismatched files, out-of-range flags
@case
def empty_transforms_json(ws, fixtures):
    scene = ws.scene()
    (scene / "transforms.json").write_text("")
    return Expect(ns_train(ws, scene), needles=[f"{scene / 'transforms.json'} is empty"], new_paths=NS_TRAIN_RUN_FILES)


@case
def transforms_json_without_frames(ws, fixtures):
    scene = ws.scene()

    def no_frames(meta):
        meta["frames"] = []
        _drop_splits(meta)

    edit_transforms(scene, no_frames)
    return Expect(
        ns_train(ws, scene),
        needles=[f"{scene / 'transforms.json'} lists no frames", "ns-process-data"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def transforms_json_that_is_a_list(ws, fixtures):
    scene = ws.scene()
    meta = json.loads((scene / "transforms.json").read_text())
    (scene / "transforms.json").write_text(json.dumps(meta["frames"]))
    return Expect(
        ns_train(ws, scene),
        needles=[f"{scene / 'transforms.json'} lists no frames (a 'frames' list"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def transforms_json_not_utf8(ws, fixtures):
    scene = ws.scene()
    path = scene / "transforms.json"
    text = path.read_text().replace('"frames"', '"note": "caf\\u00e9", "frames"', 1)
    path.write_bytes(text.replace("caf\\u00e9", "caf\u00e9").encode("latin-1"))  # Windows-1252 from an editor
    return Expect(
        ns_train(ws, scene),
        needles=[f"{path} is not UTF-8 text (byte 0xe9", "save it as UTF-8"],
        forbidden=["codec can't decode"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def unreadable_transforms_json(ws, fixtures):
    scene = ws.scene()
    path = ws.unreadable(scene / "transforms.json")
    return Expect(
        ns_train(ws, scene),
        needles=[f"{path} cannot be read (Permission denied)", "make it readable"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def empty_image_file(ws, fixtures):
    scene = ws.scene()
    image = scene / "images" / "frame_00004.png"
    image.write_bytes(b"")
    return Expect(
        ns_train(ws, scene),
        needles=[f"image {image} is empty (0 bytes)", "replace it"],
        forbidden=["not an image format"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def unreadable_training_image(ws, fixtures):
    scene = ws.scene()
    image = ws.unreadable(scene / "images" / "frame_00004.png")
    return Expect(
        ns_train(ws, scene),
        needles=[f"image {image} cannot be read (Permission denied)", "make it readable"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def image_that_is_a_symlink_loop(ws, fixtures):
    scene = ws.scene()
    image = scene / "images" / "frame_00006.png"
    image.unlink()
    image.symlink_to(image.name)  # points at itself
    return Expect(
        ns_train(ws, scene),
        needles=[f"(first: {image}, a symbolic link to frame_00006.png that leads to no file)"],
        new_paths=NS_TRAIN_RUN_FILES,
    )


@case
def label_image_of_another_size(ws, fixtures):
    scene = ws.scene()
    label = scene / "instances" / "frame_00002.png"
    Image.fromarray(np.array(Image.open(label))).resize((64, 64), Image.NEAREST).save(label)
    # found while the masks are made (the views before it stay cached for the next run)
    return Expect(
        ns_train(ws, scene),
        needles=[
            f"label image {label} of the same view is 64x64",
            "save every level's label image of a view at one size",
        ],
        new_paths=NS_TRAIN_RUN_FILES + ("cache", "cache/*", "cache/*/*"),
    )


@case
def mask_folder_with_fewer_masks_than_images(ws, fixtures):
    scene = ws.scene()
    mask_folder = ws.root / "masks"
    shutil.copytree(scene / "instances", mask_folder / "instance")
    for number in (3, 4, 5):
        (mask_folder / "instance" / f"frame_{number:05d}.png").unlink()
    argv = masks(scene, "--source", "folder", "--mask-folder", str(mask_folder), "--cache-dir", str(ws.root / "cache"))
    # found while the masks are made: the views before it are complete cache entries, kept for the next run
    return Expect(
        argv,
        needles=[f"missing label image {mask_folder / 'instance' / 'frame_00003.png'}", "one PNG per image"],
        new_paths=("cache", "cache/**"),
    )


@case
def votesplat_masks_on_an_empty_folder(ws, fixtures):
    empty = ws.root / "empty"
    empty.mkdir()
    return Expect(
        masks(empty, "--cache-dir", str(ws.root / "cache")),
        needles=[f"--data {empty}: this folder holds no transforms.json", "ns-process-data"],
    )


@case
def export_into_the_run_folder(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    return Expect(
        ns_export(config, config.parent),
        needles=[f"--output-dir {config.parent} is a non-empty folder that is not a previous instance export"],
    )


@case
def export_with_zero_mask_check_views(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    return Expect(
        ns_export(config, ws.root / "export", "--mask-check-views", "0"),
        needles=["--mask-check-views 0: the mask check needs 1 or more training views", "--mask-check False"],
    )


@case
def export_with_negative_mask_check_views(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    return Expect(
        ns_export(config, ws.root / "export", "--mask-check-views", "-3"),
        needles=["--mask-check-views -3: the mask check needs 1 or more training views"],
    )


@case
def unreadable_checkpoint(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    checkpoint = ws.unreadable(checkpoint_of(config))
    return Expect(
        ns_export(config, ws.root / "export"),
        needles=[f"checkpoint {checkpoint} (of --load-config {config}) cannot be read (Permission denied)", "chmod"],
    )


@case
def empty_run_config(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    config.write_text("")
    return Expect(ns_export(config, ws.root / "export"), needles=[f"--load-config {config}: the file is empty"])


@case
def unreadable_run_config(ws, fixtures):
    config = ws.unreadable(copy_run(fixtures.trained_demo, ws.root / "run"))
    return Expect(
        ns_export(config, ws.root / "export"),
        needles=[f"--load-config {config}: cannot be read (Permission denied)", "make it readable"],
        forbidden=["not a nerfstudio run config"],
    )


@case
def click_outside_the_image(ws, fixtures):
    argv = votesplat(
        "click", fixtures.trained_demo, "--view", "0", "--x", "1000", "--y", "64", "--output-dir", str(ws.root / "sel")
    )
    return Expect(argv, needles=["--x 1000.0 --y 64.0 is outside training view 0", "give --x in [0, 128)"])


@case
def click_on_a_view_that_does_not_exist(ws, fixtures):
    argv = votesplat(
        "click", fixtures.trained_demo, "--view", "999", "--x", "64", "--y", "64", "--output-dir", str(ws.root / "sel")
    )
    return Expect(argv, needles=["view 999 is out of range: this run has 30 training views", "--view"])


@case
def query_with_blank_text(ws, fixtures):
    argv = votesplat("query", fixtures.trained_demo, "   ", "--clip-random-init", "--clip-model", "ViT-S-32-alt")
    return Expect(argv, needles=["the text query is empty"])


@case
def data_flag_to_the_run_config(ws, fixtures):
    config = moved_dataset_run(ws, fixtures)
    argv = votesplat("click", config, "--view", "0", "--x", "64", "--y", "64", "--output-dir", str(ws.root / "sel"))
    return Expect(argv + ["--data", str(config)], needles=[f"--data {config} is a file, not a dataset"])


@case
def retrofit_from_a_ply_without_gaussians(ws, fixtures):
    from votesplat_ns.core.ply_io import read_vertex_ply, write_vertex_ply

    source = ws.root / "point_cloud.ply"
    columns = read_vertex_ply(fixtures.previous_export / "scene.ply")
    write_vertex_ply(source, {name: column[:0] for name, column in columns.items()})
    argv = ns_train(ws, DEMO_SCENE, *ONE_VOTE_STEP, "--pipeline.model.retrofit-from", str(source))
    return Expect(
        argv,
        needles=[f"--pipeline.model.retrofit-from {source}", "no Gaussians"],
        new_paths=("runs", "runs/**", "cache", "cache/**"),
    )


@case
def retrofit_from_a_ply_with_nan_positions(ws, fixtures):
    from votesplat_ns.core.ply_io import read_vertex_ply, write_vertex_ply

    source = ws.root / "point_cloud.ply"
    columns = read_vertex_ply(fixtures.previous_export / "scene.ply")
    columns["x"][:5] = np.nan
    write_vertex_ply(source, columns)
    argv = ns_train(ws, DEMO_SCENE, *ONE_VOTE_STEP, "--pipeline.model.retrofit-from", str(source))
    return Expect(
        argv,
        needles=[f"--pipeline.model.retrofit-from {source}", "NaN"],
        new_paths=("runs", "runs/**", "cache", "cache/**"),
    )


# ---- a full disk (simulated: a tmpfs cannot be mounted everywhere the tests run)
class FullDisk:
    """A disk that fills up: once ``room`` bytes have gone into files opened under ``folder``, a write there stores
    what still fits and fails as write() does on a full disk (OSError ENOSPC, naming no file).

    Installed with ``monkeypatch`` over ``os.fdopen``, which every atomic write of the plugin opens its file with
    (``core/ply_io.atomic_write``)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, folder: Path, room: int = 0):
        self.folder = Path(os.path.abspath(folder))
        self.room = room
        self.lock = threading.Lock()
        real_fdopen = os.fdopen

        def fdopen(fd, *args, **kwargs):
            handle = real_fdopen(fd, *args, **kwargs)
            with contextlib.suppress(OSError):
                path = Path(os.readlink(f"/proc/self/fd/{fd}"))
                if self.folder in path.parents:
                    return _FillingFile(handle, self)
            return handle

        monkeypatch.setattr(os, "fdopen", fdopen)

    def take(self, size: int) -> int:
        """How many of ``size`` bytes still fit."""
        with self.lock:
            fits = min(size, self.room)
            self.room -= fits
            return fits


class _FillingFile:
    def __init__(self, handle, disk: FullDisk):
        self._handle = handle
        self._disk = disk

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        fits = self._disk.take(view.nbytes)
        self._handle.write(view[:fits])
        if fits < view.nbytes:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return fits

    def __getattr__(self, name: str):
        if name in ("_handle", "_disk"):  # not set yet (an object made without __init__): no endless recursion
            raise AttributeError(name)
        return getattr(self._handle, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self._handle.close()


def votesplat_in_process(*args: str) -> Callable[[], object]:
    """The ``votesplat`` command's main on ``args``, for a case run in-process."""
    from votesplat_ns.cli.main import main

    return lambda: main(list(args))


@case
def disk_full_during_export(ws, fixtures):
    config = copy_run(fixtures.trained_demo, ws.root / "run")
    exports = ws.root / "exports"
    target = exports / "export"
    shutil.copytree(fixtures.previous_export, target)  # the previous export must survive
    FullDisk(ws.monkeypatch, exports, room=100_000)  # scene.ply stops part-way
    argv = ["votesplat", "export", "--load-config", str(config), "--output-dir", str(target), "--num-views", "0"]
    return Expect(
        argv,
        call=votesplat_in_process(*argv[1:]),
        needles=[f"--output-dir {target}: the disk is full", "scene.ply", "nothing was left half-written"],
        new_paths=("run/*/*/*/votesplat_instances", "run/*/*/*/votesplat_instances/**"),
    )


@case
def disk_full_during_the_vote_cache_build(ws, fixtures):
    scene = ws.scene()
    cache = ws.root / "cache"
    FullDisk(ws.monkeypatch, cache, room=300_000)  # a few views' entries fit
    argv = ["votesplat", "masks", "--data", str(scene), "--cache-dir", str(cache)]

    def finished_entries_stay_usable():
        records = sorted(cache.glob("*/*.votes.npz"))
        assert records, "no entry was finished before the disk filled up"
        for path in records:  # an entry is its record and the labels file the record describes
            with np.load(path) as record:
                shape = tuple(int(v) for v in record["labels_shape"])
            assert np.load(path.with_name(path.name.replace(".votes.npz", ".labels.npy"))).shape == shape

    return Expect(
        argv,
        call=votesplat_in_process(*argv[1:]),
        # the file that filled the disk is named: a labels .npy or a .votes.npz record, whichever write came first
        needles=[f"--cache-dir {cache}: the disk is full", f"while writing {cache}/", "nothing was left half-written"],
        new_paths=("cache", "cache/*", "cache/*/*"),
        after=finished_entries_stay_usable,
    )


def test_a_short_write_is_named_as_a_full_disk_only_when_the_disk_is_full(tmp_path, monkeypatch):
    """numpy's write onto a full disk (np.save: "32768 requested and 6080 written") has no errno and names no file."""
    from types import SimpleNamespace

    from votesplat_ns.core.ply_io import atomic_write
    from votesplat_ns.errors import input_error_for_write

    target = tmp_path / "entry.labels.npy"
    for free_blocks, expected in ((0, errno.ENOSPC), (10**6, errno.EIO)):
        monkeypatch.setattr(os, "statvfs", lambda path, free=free_blocks: SimpleNamespace(f_bavail=free, f_frsize=4096))
        with pytest.raises(OSError) as raised:
            with atomic_write(target) as handle:
                handle.write(b"x" * 6080)
                raise OSError("32768 requested and 6080 written")
        assert (raised.value.errno, raised.value.filename) == (expected, str(target))
        assert list(tmp_path.iterdir()) == []  # the temporary file is gone
    disk_full = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(target))
    line = str(input_error_for_write(disk_full, tmp_path, "--cache-dir"))
    assert line.startswith(f"--cache-dir {tmp_path}: the disk is full") and str(target) in line


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
def query_eval_labels_folder_missing(ws, fixtures):
    missing = ws.root / "labels"
    argv = votesplat("query-eval", fixtures.trained_demo, "--labels", str(missing))
    argv += ["--clip-random-init", "--clip-model", "ViT-S-32-alt"]
    return Expect(argv, needles=[f"--labels {missing}: folder not found"], forbidden=["frame_*.json label files"])


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
    if name in ("ns-viewer",):  # a command without subcommands
        return name
    return PROGRAMS.get(name, f"{name} {argv[1]}")


@dataclass
class Ran:
    returncode: int
    stdout: str
    stderr: str


def run_command(ws: Workspace, argv: Sequence[str], cwd: Path, preloaded: Optional[PreloadedScripts]) -> Ran:
    """``argv`` in a process of its own (conftest.py ``run_script``: a fork of its console script's preloaded
    runner where there is one that can run it); for a case that made a folder read-only, without the capabilities
    that let root ignore file permissions, as ``setpriv`` (DROP_ROOT_OVERRIDES) leaves a command it executes (the
    fork drops them itself, into the same capability sets: the runner checks them)."""
    drop = ws.drop_root_overrides
    result = run_script(
        argv,
        command_env(ws.home),
        cwd,
        preloaded,
        drop_capabilities=list(ROOT_OVERRIDES.values()) if drop else [],
        fresh_prefix=DROP_ROOT_OVERRIDES if drop else [],
    )
    return Ran(result.returncode, result.stdout, result.stderr)


def run_in_process(call: Callable[[], object], argv: Sequence[str], cwd: Path) -> Ran:
    """``call()`` under ``argv`` with its stdout, stderr and warnings captured; an exception it lets out is printed
    as Python would."""
    out, err = io.StringIO(), io.StringIO()
    returncode = 0
    previous, previous_argv = os.getcwd(), sys.argv
    # A user's Ctrl-C raises KeyboardInterrupt; a pytest started in the background ignores SIGINT instead
    previous_sigint = signal.signal(signal.SIGINT, signal.default_int_handler)
    os.chdir(cwd)
    sys.argv = list(argv)

    def show(message, category, filename, lineno, file=None, line=None):
        err.write(warnings.formatwarning(message, category, filename, lineno, line))

    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), warnings.catch_warnings():
            warnings.simplefilter("default")
            warnings.showwarning = show
            try:
                call()
            except SystemExit as exit:
                returncode = exit.code if isinstance(exit.code, int) else 1
            except BaseException:  # noqa: BLE001 - what escapes the command is what the user would see
                err.write(traceback.format_exc())
                returncode = 1
    finally:
        os.chdir(previous)
        sys.argv = previous_argv
        signal.signal(signal.SIGINT, previous_sigint)
    return Ran(returncode, out.getvalue(), err.getvalue())


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


# What a case can end in. The first two are right (which one a case expects is its exit code); the others are
# what the probe counts as failures.
ONE_LINE = "ended in one clear line"
RAN_ON = "ran on with what it had to say"
TRACEBACK = "traceback"
SILENT_WRONG = "silent wrong"
DATA_LOST = "data lost"
UNCLEAR = "unclear or misleading message"
LEFTOVERS = "left files behind"
VERDICTS = (ONE_LINE, RAN_ON, TRACEBACK, SILENT_WRONG, DATA_LOST, UNCLEAR, LEFTOVERS)


@dataclass
class Outcome:
    verdict: str
    detail: str = ""


def judge(name: str, expect: Expect, ran: Ran, before: Dict[str, str], after: Dict[str, str]) -> Outcome:
    """What a case ended in (see VERDICTS), and why when it is wrong."""
    output = ran.stdout + ran.stderr
    tail = output[-4000:]
    if "Traceback" in output:
        return Outcome(TRACEBACK, tail)
    changed = [
        path
        for path in before
        if path in after and after[path] != before[path] and not matches(path, expect.changed_paths)
    ]
    removed = [path for path in before if path not in after and not matches(path, expect.removed_paths)]
    if changed or removed:
        return Outcome(DATA_LOST, f"{name} changed {changed} and removed {removed}")
    if ran.returncode != expect.exit_code:
        verdict = SILENT_WRONG if ran.returncode == 0 else UNCLEAR
        return Outcome(verdict, f"exit code {ran.returncode}, expected {expect.exit_code}: {tail}")
    forbidden = [text for text in expect.forbidden if text in output]
    if forbidden:
        return Outcome(UNCLEAR, f"says {forbidden}: {tail}")
    if expect.exit_code != 0:
        errors = [line for line in ran.stderr.splitlines() if expect.line in line]
        lines = [line for line in ran.stderr.splitlines() if line.strip()]
        if (
            len(errors) != 1
            or lines[-1] != errors[0]
            or not errors[0].startswith(program_of(expect.argv) + expect.line)
        ):
            return Outcome(UNCLEAR, f"not one error line at the end: {ran.stderr[-4000:]}")
        missing = [needle for needle in expect.needles if needle not in errors[0]]
        if missing:
            return Outcome(UNCLEAR, f"the line lacks {missing}: {errors[0]}")
    else:
        wrong = [needle for needle in expect.needles if output.count(needle) != 1]
        if wrong:
            return Outcome(SILENT_WRONG, f"not said once: {wrong}: {tail}")
    unexpected = [path for path in after if path not in before and not matches(path, expect.new_paths)]
    leftovers = [
        path for path in after if path not in before and any(marker in Path(path).name for marker in TEMP_MARKERS)
    ]
    if unexpected or leftovers:
        return Outcome(LEFTOVERS, f"{name} left {unexpected + leftovers}")
    if expect.after is not None:
        try:
            expect.after()
        except AssertionError as error:
            return Outcome(SILENT_WRONG, f"{name}: {error}")
    return Outcome(ONE_LINE if expect.exit_code != 0 else RAN_ON)


def run_case(name: str, ws: Workspace, fixtures: "Fixtures", preloaded: Optional[PreloadedScripts] = None) -> Outcome:
    """Set up case ``name`` in ``ws``, run its command and judge what it did."""
    expect = CASES[name](ws, fixtures)
    before = snapshot(ws.root)
    cwd = expect.cwd or ws.home
    if expect.call is not None:
        ran = run_in_process(expect.call, expect.argv, cwd)
        ws.monkeypatch.undo()  # the fault ends with the command
    else:
        ran = run_command(ws, expect.argv, cwd, preloaded)
    ws.unlock()
    return judge(name, expect, ran, before, snapshot(ws.root))


@dataclass
class Fixtures:
    trained_demo: Path
    previous_export: Path


@pytest.fixture(scope="module")
def fixtures(trained_demo, preloaded, tmp_path_factory) -> Fixtures:
    """A copy of the trained demo run and an instance export of it (ns-export, as a user would make it)."""
    base = tmp_path_factory.mktemp("bad_inputs")
    config = copy_run(trained_demo, base / "run")
    export = base / "export"
    result = run_script(ns_export(config, export), command_env(), Path.cwd(), preloaded)
    assert result.returncode == 0, result.stderr[-3000:]
    return Fixtures(trained_demo=config, previous_export=export)


@pytest.fixture
def workspace(tmp_path, monkeypatch):
    ws = Workspace(tmp_path, monkeypatch)
    yield ws
    ws.unlock()


class Probe:
    """The outcome of every case run in this session; conftest.py's ``pytest_terminal_summary`` prints :meth:`summary`."""

    def __init__(self) -> None:
        self.outcomes: Dict[str, Outcome] = {}

    def summary(self) -> List[str]:
        """Cases tried, and how many ended in each way; then each case that ended wrongly."""
        outcomes = self.outcomes
        counts = {verdict: sum(outcome.verdict == verdict for outcome in outcomes.values()) for verdict in VERDICTS}
        lines = [
            f"bad-input probe: {len(outcomes)} cases tried; {counts[ONE_LINE]} ended in one clear line, "
            f"{counts[RAN_ON]} ran on with what they had to say; tracebacks {counts[TRACEBACK]}, "
            f"silent wrong {counts[SILENT_WRONG]}, data lost {counts[DATA_LOST]}, "
            f"unclear messages {counts[UNCLEAR]}, left files behind {counts[LEFTOVERS]}"
        ]
        wrong = [
            (name, outcome) for name, outcome in sorted(outcomes.items()) if outcome.verdict not in (ONE_LINE, RAN_ON)
        ]
        return lines + [f"  {name}: {outcome.verdict}" for name, outcome in wrong]


@pytest.fixture(scope="session")
def probe(request) -> Probe:
    found = Probe()
    request.config.votesplat_bad_input_probe = found
    return found


@pytest.mark.slow  # every case starts a console script; several train a step or load a trained run
@pytest.mark.parametrize("name", sorted(CASES))
def test_bad_input(name, workspace, fixtures, preloaded, probe):
    outcome = run_case(name, workspace, fixtures, preloaded)
    probe.outcomes[name] = outcome
    assert outcome.verdict in (ONE_LINE, RAN_ON), f"{outcome.verdict}: {outcome.detail}"
