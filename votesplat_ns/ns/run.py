"""A trained run through nerfstudio: the one checkpoint loader and the one camera-to-view conversion.

:func:`load_run` is nerfstudio's ``eval_setup`` with one-line errors (:func:`check_run` checks the config.yml,
read without running code by ``ns/run_config.py`` ``load_run_config``, and its checkpoint first), reading the
checkpoint with ``weights_only=True``, and returns the run as a :class:`~votesplat_ns.core.scene.TrainedScene`; :func:`latest_checkpoint`
and :func:`load_gaussians` read only the Gaussians of a run's checkpoint (a retrofit's source). :func:`camera_view` and
:func:`dataset_views` turn nerfstudio ``Cameras`` into :class:`~votesplat_ns.core.cameras.PinholeView`s
(gsplat's conventions). The checkpoint safe-globals are registered when ``votesplat_ns`` is imported.
"""

from __future__ import annotations

import contextlib
import zipfile
from pathlib import Path
from typing import Any, Callable, Dict, List, NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from votesplat_ns.core.cameras import PinholeView, viewmat_from_camera_to_world
from votesplat_ns.core.ply_io import SH_C0
from votesplat_ns.core.scene import TrainedScene
from votesplat_ns.errors import VoteSplatInputError, file_format_problem, load_failure_reason
from votesplat_ns.ns.run_config import load_run_config, not_a_run_config

SPLAT_PARAM_NAMES = ("means", "scales", "quats", "features_dc", "features_rest", "opacities")
DAMAGED_HINT = "use a run whose training finished, or train again (a kill during a save can leave a partial file)"
PICKLED_OBJECTS = "it holds Python objects besides weights, which could run code when loaded"
FOREIGN_HINT = "ns-train did not write it: do not load it, and use a run you trust"


def _run_checkpoint(config) -> Optional[Path]:
    """The step-*.ckpt nerfstudio's eval_setup loads for a run config (the newest), or None.

    Always from the run's own checkpoint folder: a resumed run's ``load_dir`` names the run it started from."""
    folder = Path(config.get_checkpoint_dir())
    if getattr(config, "load_step", None) is not None:
        return folder / f"step-{config.load_step:09d}.ckpt"
    checkpoints = sorted(folder.glob("step-*.ckpt")) if folder.is_dir() else []
    return checkpoints[-1] if checkpoints else None


def checkpoint_problem(checkpoint: Path) -> Optional[str]:
    """Why ``checkpoint`` cannot be loaded (it is read again only on this error path), or None."""
    try:
        torch.load(checkpoint, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for a damaged file
        return load_failure_reason(error, checkpoint)
    return None


def check_run(load_config: Union[str, Path], flag: str = "--load-config") -> Path:
    """The checkpoint :func:`load_run` will load for a run's config.yml, checked before any model is built.

    A missing config file, a run without checkpoints or a checkpoint that is truncated or damaged
    raise :class:`VoteSplatInputError` naming the file.
    """
    load_config = Path(load_config)
    return checked_checkpoint(load_run_config(load_config, flag), load_config, flag)


def checked_checkpoint(config: Any, load_config: Path, flag: str = "--load-config") -> Path:
    """:func:`check_run` on a config already read from ``load_config``."""
    try:
        checkpoint = _run_checkpoint(config) if hasattr(config, "get_checkpoint_dir") else None
    except Exception as error:  # a YAML file that is not a nerfstudio run config
        raise not_a_run_config(load_config, flag, error) from None
    if checkpoint is None or not checkpoint.is_file():
        folder = checkpoint.parent if checkpoint is not None else "its nerfstudio_models/ folder"
        raise VoteSplatInputError(
            f"{flag} {load_config}: the run has no checkpoint (looked in {folder}); "
            "train it (checkpoints are written every --steps-per-save steps and at the end) or pass another run"
        )
    try:
        with open(checkpoint, "rb"):
            pass
    except OSError as error:
        raise VoteSplatInputError(
            f"checkpoint {checkpoint} (of {flag} {load_config}) cannot be read ({error.strerror or error}); "
            "make it readable (e.g. chmod a+r), or pass another run"
        ) from None
    problem = file_format_problem(checkpoint)  # before the model is built
    if problem is not None:
        raise VoteSplatInputError(
            f"checkpoint {checkpoint} (of {flag} {load_config}) cannot be loaded: {problem}; "
            "use a run whose training finished, or train again (a kill during a save can leave a partial file)"
        )
    return checkpoint


class DatasetMissing(VoteSplatInputError):
    """The run's dataset is not where its config.yml says (moved or deleted), and no ``--data`` gave its new place."""

    def __init__(self, message: str, dataset: Path, data_flag: str):
        super().__init__(message)
        self.dataset = dataset
        self.data_flag = data_flag

    @property
    def reason(self) -> str:
        """What is missing and what to do, for a command that goes on without the dataset."""
        return f"the run's dataset {self.dataset} is not there; pass its folder with {self.data_flag}"


def run_dataset(config: Any) -> Optional[Path]:
    """The dataset a run config reads (its datamanager's data, else its dataparser's), or None."""
    datamanager = config.pipeline.datamanager
    data = getattr(datamanager, "data", None) or getattr(getattr(datamanager, "dataparser", None), "data", None)
    return Path(data) if data is not None else None


def use_dataset(config: Any, data: Optional[Path], load_config: Path, flag: str, data_flag: str = "--data") -> None:
    """Point ``config`` at ``data`` (given: checked first) and check that the run's dataset is there.

    A dataset that moved raises :class:`DatasetMissing` naming ``data_flag``; one that is there but is not a
    dataset (no transforms.json) raises :class:`VoteSplatInputError` naming it too."""
    from votesplat_ns.ns.data_checks import check_data_input

    if data is not None:
        data = Path(data)
        if not data.exists():
            raise VoteSplatInputError(
                f"{data_flag} {data}: folder not found; give the folder of the run's dataset (it holds transforms.json)"
            )
        config.data = data
        config.pipeline.datamanager.data = data
    dataset = run_dataset(config)
    datamanager = config.pipeline.datamanager
    if dataset is None or not hasattr(datamanager, "dataset_path"):  # not a votesplat run: said later
        return
    if data is None and not dataset.exists():
        raise DatasetMissing(
            f"{flag} {load_config}: the run's dataset {dataset} is not there (moved or deleted); "
            f"pass its folder with {data_flag}",
            dataset,
            data_flag,
        )
    where = f"{data_flag} {data}" if data is not None else f"the run's dataset {dataset}"
    try:
        check_data_input(datamanager, check_images=False, where=where)
    except VoteSplatInputError as error:
        if data is not None:
            raise
        raise VoteSplatInputError(f"{error}; if the dataset moved, pass its folder with {data_flag}") from None


class LoadedRun(NamedTuple):
    pipeline: Any  # nerfstudio Pipeline (model, datamanager)
    scene: TrainedScene
    step: int


def load_run(
    load_config: Union[str, Path],
    flag: str = "--load-config",
    test_mode: str = "inference",
    update_config_callback: Optional[Callable[[Any], Any]] = None,
    data: Optional[Path] = None,
    data_flag: str = "--data",
) -> LoadedRun:
    """Load a run's newest checkpoint as nerfstudio's ``eval_setup`` does, without running code from its files.

    The config.yml is read by :func:`~votesplat_ns.ns.run_config.load_run_config` (config classes, paths, enums
    and tuples only; nerfstudio's ``eval_setup`` reads it with ``yaml.Loader``, which builds anything) and the
    checkpoint with ``weights_only=True``. A missing config file, one that names anything else, a run without
    checkpoints or a damaged checkpoint raise :class:`VoteSplatInputError` naming the file, before the model is
    built where possible; a checkpoint without votes raises ``ValueError`` (not a votesplat run). ``data``
    (the command's ``data_flag``) replaces the run's dataset, which moved; without it, a dataset that is not
    there raises :class:`DatasetMissing` naming ``data_flag``.
    """
    load_config = Path(load_config)
    config = load_run_config(load_config, flag)
    checked_checkpoint(config, load_config, flag)  # before any model is built
    use_dataset(config, data, load_config, flag, data_flag)
    pipeline, _, step = setup_run(config, load_config, flag, test_mode, update_config_callback)
    return LoadedRun(pipeline, TrainedScene.from_model(pipeline.model), step)


def setup_run(
    config: Any,
    load_config: Path,
    flag: str = "--load-config",
    test_mode: str = "inference",
    update_config_callback: Optional[Callable[[Any], Any]] = None,
) -> Tuple[Any, Path, int]:
    """(pipeline, checkpoint, step): nerfstudio 1.1.5 ``eval_setup``'s steps on a config already loaded, the
    checkpoint read with ``weights_only=True`` whatever torch's default (``TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD``
    changes only calls that do not say)."""
    from nerfstudio.configs.method_configs import all_methods  # imports the method configs, which import us
    from nerfstudio.utils.rich_utils import CONSOLE

    if config.method_name not in all_methods:
        raise VoteSplatInputError(
            f"{flag} {load_config}: the run was trained with method {config.method_name!r}, which is not installed here"
        )
    config.pipeline.datamanager._target = all_methods[config.method_name].pipeline.datamanager._target
    if update_config_callback is not None:
        config = update_config_callback(config)
    config.load_dir = config.get_checkpoint_dir()
    if config.load_step is not None:
        checkpoint = Path(config.load_dir) / f"step-{config.load_step:09d}.ckpt"
    else:
        found = sorted(Path(config.load_dir).glob("step-*.ckpt")) if Path(config.load_dir).is_dir() else []
        checkpoint = found[-1] if found else Path(config.load_dir) / "step-*.ckpt"
    if not checkpoint.is_file():
        raise VoteSplatInputError(
            f"{flag} {load_config}: the run has no checkpoint (looked in {config.load_dir}); "
            "train it (checkpoints are written every --steps-per-save steps and at the end) or pass another run"
        )
    state = read_run_checkpoint(checkpoint, load_config, flag)  # before the model is built
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    pipeline = config.pipeline.setup(device=device, test_mode=test_mode)
    pipeline.eval()
    pipeline.load_pipeline(state["pipeline"], state["step"])
    CONSOLE.print(f":white_check_mark: Done loading checkpoint from {checkpoint}")
    return pipeline, checkpoint, int(state["step"])


def read_run_checkpoint(checkpoint: Path, load_config: Path, flag: str = "--load-config") -> Dict[str, Any]:
    """A run's checkpoint read with ``weights_only=True``; one line naming it when it cannot be used."""
    try:
        state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for a damaged or foreign file
        reason = checkpoint_failure_reason(error, checkpoint)
        hint = FOREIGN_HINT if reason == PICKLED_OBJECTS else DAMAGED_HINT
        raise VoteSplatInputError(
            f"checkpoint {checkpoint} (of {flag} {load_config}) cannot be loaded: {reason}; {hint}"
        ) from None
    if not isinstance(state, dict) or not {"step", "pipeline"} <= set(state):
        raise VoteSplatInputError(
            f"checkpoint {checkpoint} (of {flag} {load_config}) is not a nerfstudio checkpoint (no step and pipeline); "
            f"{DAMAGED_HINT}"
        )
    return state


def run_level_names(config: Any, count: int) -> Tuple[str, ...]:
    """The names of a run's ``count`` vote levels, from its config alone (the model resolves them from the dataset).

    The model's ``vote_levels`` or the datamanager's ``mask_levels`` when set; else those of its mask source
    (``auto``: the dataset's or SAM's, whichever has ``count``); ``level_<i>`` when none fits."""
    from votesplat_ns.core.mask_sources import FolderMaskSource
    from votesplat_ns.core.sam_masks import SAM_LEVELS
    from votesplat_ns.ns.data_checks import DATASET_LEVELS

    datamanager = config.pipeline.datamanager
    candidates = [getattr(config.pipeline.model, "vote_levels", None), getattr(datamanager, "mask_levels", None)]
    source = getattr(datamanager, "mask_source", "auto")
    if source in ("dataset", "auto"):
        candidates.append(DATASET_LEVELS)
    if source in ("sam", "auto"):
        candidates.append(SAM_LEVELS)
    folder = getattr(datamanager, "mask_folder", None)
    if source == "folder" and folder is not None:
        with contextlib.suppress(OSError, ValueError):  # the folder moved with the dataset
            candidates.append(FolderMaskSource(Path(folder)).levels)
    for names in candidates:
        if names and len(names) == count:
            return tuple(str(name) for name in names)
    return tuple(f"level_{index}" for index in range(count))


def load_run_scene(load_config: Union[str, Path], flag: str = "--load-config") -> Tuple[TrainedScene, int]:
    """(scene, step) of a run from its checkpoint alone: no model is built and no dataset read, so it works once the
    dataset has moved. The same checks as :func:`load_run`; the level names come from :func:`run_level_names`."""
    from votesplat_ns.core.scene import VOTE_OFFSETS_KEY

    load_config = Path(load_config)
    config = load_run_config(load_config, flag)
    checkpoint = checked_checkpoint(config, load_config, flag)
    state = read_run_checkpoint(checkpoint, load_config, flag)
    prefix = "_model.gauss_params."
    params = {key[len(prefix) :]: value for key, value in state["pipeline"].items() if key.startswith(prefix)}
    offsets = params.get(VOTE_OFFSETS_KEY)
    count = int(offsets.shape[1]) if offsets is not None and offsets.ndim == 3 else 1
    model = config.pipeline.model
    scene = TrainedScene.from_params(params, run_level_names(config, count), getattr(model, "sh_degree", None))
    return scene, int(state["step"])


def latest_checkpoint(path: Path, flag: str = "--pipeline.model.retrofit-from") -> Path:
    """``path`` itself if it is a .ckpt file, else the newest step-*.ckpt under it (or its nerfstudio_models/).

    Anything else raises one line naming ``flag``."""
    path = Path(path)
    if path.suffix == ".ckpt" and path.is_file():
        return path
    if path.name == "config.yml":
        path = path.parent
    if path.is_file():
        raise VoteSplatInputError(
            f"{flag} {path}: not a checkpoint; give a step-*.ckpt file, a run folder with nerfstudio_models/ or a 3DGS .ply"
        )
    candidates = sorted(path.glob("step-*.ckpt")) or sorted(path.glob("nerfstudio_models/step-*.ckpt"))
    if not candidates:
        raise VoteSplatInputError(
            f"{flag} {path}: no checkpoint found there; give a step-*.ckpt file, a run folder with nerfstudio_models/ "
            "or a 3DGS .ply"
        )
    return candidates[-1]


def checkpoint_failure_reason(error: BaseException, path: Path) -> str:
    """Why ``torch.load(path, weights_only=True)`` failed, in a few words that never advise ``weights_only=False``."""
    if zipfile.is_zipfile(path) and "Weights only load failed" in str(error):
        return PICKLED_OBJECTS
    return load_failure_reason(error, path)


def load_gaussians(
    checkpoint: Path, names: Sequence[str] = SPLAT_PARAM_NAMES, flag: str = "--pipeline.model.retrofit-from"
) -> Dict[str, torch.Tensor]:
    """splatfacto's Gaussian parameters (or the ``gauss_params`` in ``names``, e.g. with a votesplat run's
    vote offsets and support) from a nerfstudio checkpoint (splatfacto or votesplat), read with
    ``weights_only=True``: a file that is not one (a pickle of anything else) raises one line naming ``flag``."""
    try:
        state = torch.load(checkpoint, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for a file that is not a checkpoint
        raise VoteSplatInputError(
            f"{flag} {checkpoint} cannot be loaded: {checkpoint_failure_reason(error, checkpoint)}; "
            "give a step-*.ckpt written by ns-train splatfacto or votesplat, its run folder, or a 3DGS .ply"
        ) from None
    pipeline_state = state.get("pipeline", {}) if isinstance(state, dict) else {}
    missing = [name for name in names if f"_model.gauss_params.{name}" not in pipeline_state]
    if missing:
        raise VoteSplatInputError(
            f"{flag} {checkpoint} is not a splatfacto checkpoint (no {', '.join(missing)} Gaussians); "
            "retrofit needs one written by ns-train splatfacto or votesplat"
        )
    return {name: pipeline_state[f"_model.gauss_params.{name}"] for name in names}


def gaussians_from_ply_arrays(arrays: Dict[str, np.ndarray]) -> Dict[str, torch.Tensor]:
    """``ply_io.read_3dgs_ply`` arrays as splatfacto's Gaussian parameters (opacities [N, 1])."""
    return {
        "means": torch.from_numpy(arrays["means"]),
        "scales": torch.from_numpy(arrays["log_scales"]),
        "quats": torch.from_numpy(arrays["quats"]),
        "features_dc": torch.from_numpy(arrays["features_dc"]),
        "features_rest": torch.from_numpy(arrays["features_rest"]),
        "opacities": torch.from_numpy(arrays["opacity_logits"])[:, None],
    }


def splatfacto_dc_from_ply(features_dc: torch.Tensor, sh_degree: int) -> torch.Tensor:
    """A PLY's ``f_dc`` [N, 3] as splatfacto's ``features_dc`` for a model of ``sh_degree``.

    A PLY always stores SH DC coefficients (colour = 0.5 + C0 * f_dc); splatfacto keeps them as such
    from degree 1 on, but at degree 0 it keeps RGB logits (colour = sigmoid(features_dc)), and
    nerfstudio's exporter writes f_dc = RGB2SH(sigmoid(features_dc)) there. So degree 0 takes the
    logit of the PLY's colour (clamped into (0, 1): other writers may store colours outside it).
    """
    if sh_degree > 0:
        return features_dc
    colour = (features_dc * SH_C0 + 0.5).clamp(1e-6, 1.0 - 1e-6)
    return torch.logit(colour)


def camera_view(cameras: Any, index: int = 0, name: str = "", dtype: torch.dtype = torch.float32) -> PinholeView:
    """Camera ``index`` of nerfstudio ``Cameras`` as the :class:`PinholeView` splatfacto renders."""
    camera = cameras[index : index + 1]
    return PinholeView(
        viewmat=viewmat_from_camera_to_world(camera.camera_to_worlds[0].to(dtype)),
        K=camera.get_intrinsics_matrices()[0].to(dtype),
        width=int(camera.width.item()),
        height=int(camera.height.item()),
        name=name,
    )


def evenly_spaced(count: int, num: int) -> List[int]:
    """Up to ``num`` indices spread evenly over ``range(count)``, first and last included."""
    if num <= 0 or count <= 0:
        return []
    return sorted({int(round(x)) for x in np.linspace(0, count - 1, min(num, count))})


def dataset_views(dataset: Any, indices: Optional[Sequence[int]] = None, cameras: Any = None) -> List[PinholeView]:
    """Views of a nerfstudio dataset's cameras (all, or ``indices``), named by their image file path.

    ``cameras`` replaces ``dataset.cameras`` (nerfstudio's undistorted cache rewrites the intrinsics).
    """
    cameras = dataset.cameras if cameras is None else cameras
    indices = range(len(cameras)) if indices is None else indices
    filenames = getattr(dataset, "image_filenames", None)
    return [camera_view(cameras, index, str(filenames[index]) if filenames is not None else "") for index in indices]
