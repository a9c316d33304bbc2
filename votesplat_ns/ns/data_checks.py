"""Checks of a training run's inputs, before any image is loaded or mask made, each failing with one
actionable line (:class:`~votesplat_ns.errors.VoteSplatInputError`): the dataset and every
frame of its transforms.json, the vote cache location, the vote loss schedule.

Used by :class:`votesplat_ns.ns.datamanager.VoteDataManager` (``ns-train``) and ``votesplat masks``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Dict, Optional, Protocol, Tuple

import numpy as np
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

from votesplat_ns.core.image_files import NERFSTUDIO_IMAGE_MODES, check_label_format, image_file_header
from votesplat_ns.errors import VoteSplatInputError

DEFAULT_OUTPUT_DIR = Path("outputs")
DATASET_LEVELS = ("instance", "part")
CACHE_FOLDER_NAME = "votesplat_cache"


class DataInput(Protocol):
    """What the dataset checks read of the datamanager's options (``VoteDataManagerConfig`` has them all)."""

    @property
    def data(self) -> Optional[Path]: ...

    @property
    def dataparser(self) -> Any: ...

    @property
    def dataset_path(self) -> Path: ...

    @property
    def mask_source(self) -> str: ...

    @property
    def mask_levels(self) -> Optional[Tuple[str, ...]]: ...


def dataset_dir(data: Path) -> Path:
    """The dataset folder for a ``--data`` argument (a folder or its transforms.json)."""
    data = Path(data)
    return data.parent if data.suffix == ".json" else data


def default_cache_dir(data: Path, output_dir: Path = DEFAULT_OUTPUT_DIR) -> Path:
    """``<output_dir>/<dataset folder name>/votesplat_cache``, matching ns-train's experiment folder."""
    name = dataset_dir(data).resolve().name or "dataset"
    return Path(output_dir) / name / CACHE_FOLDER_NAME


def check_cache_outside_dataset(cache_dir: Path, data: Path) -> None:
    cache_resolved = Path(cache_dir).resolve()
    data_resolved = dataset_dir(data).resolve()
    if cache_resolved == data_resolved or data_resolved in cache_resolved.parents:
        raise VoteSplatInputError(
            f"vote cache folder {cache_dir} lies inside the dataset {data_resolved}; "
            "pass --pipeline.datamanager.cache-dir <folder outside the dataset> (or run from another folder)"
        )


CACHE_DIR_FLAG = "--pipeline.datamanager.cache-dir"


def check_vote_schedule(model, start_step: int, num_steps: int) -> None:
    """Raise :class:`VoteSplatInputError` when no step in ``start_step .. start_step + num_steps - 1`` runs the vote loss.

    Such a run trains splatfacto only and ends with every Gaussian's vote support at zero. A
    retrofit run (vote-only) votes on every step; a run with both vote loss weights at 0 trains
    without votes on purpose (e.g. the splatfacto base of a retrofit benchmark).
    """
    config = model.config
    if getattr(model, "vote_only", False) or num_steps <= 0:
        return
    if config.vote_loss_weight == 0 and config.distortion_loss_weight == 0:
        return
    start, every = int(config.vote_start_step), max(1, int(config.vote_every_n_steps))
    first_vote = start if start_step <= start else start + -(-(start_step - start) // every) * every
    last_step = start_step + num_steps - 1
    if first_vote > last_step:
        raise VoteSplatInputError(
            f"--pipeline.model.vote-start-step {start} is past the last training step {last_step} "
            f"(--max-num-iterations {num_steps}{f', resuming at step {start_step}' if start_step else ''}): "
            "the vote loss would never run and the run would learn no instances; "
            "lower --pipeline.model.vote-start-step or raise --max-num-iterations"
        )


MAKE_DATASET_HINT = "give the folder that holds transforms.json (ns-process-data makes one from images or a video)"


def frame_image_path(data_dir: Path, file_path: str, downscale_factor: Optional[int]) -> Path:
    """The image file nerfstudio's dataparser opens for a frame (``images_N/`` with ``--downscale-factor N``)."""
    if downscale_factor is not None and downscale_factor > 1:
        return data_dir / f"images_{downscale_factor}" / Path(file_path).name
    return data_dir / file_path


def check_data_input(
    config: DataInput,
    check_images: bool = True,
    where: Optional[str] = None,
    mask_source_flag: str = "--pipeline.datamanager.mask-source",
) -> None:
    """Raise :class:`VoteSplatInputError`, saying what to do, for a dataset that would fail later or train wrongly.

    Checks that the data path exists and, for the nerfstudio dataparser, that it holds a readable
    transforms.json with frames and (``check_images``) the frames themselves (:func:`check_frames`).
    ``where`` names the path in the message (default ``--data <path>``), ``mask_source_flag`` the
    option that picks the mask source.
    """
    data = config.dataset_path
    where = where or f"--data {data}"
    nerfstudio_data = isinstance(config.dataparser, NerfstudioDataParserConfig)
    if not data.exists():
        what = "file" if data.suffix else "folder"
        hint = MAKE_DATASET_HINT if nerfstudio_data else "give the dataset folder"
        raise VoteSplatInputError(f"{where}: {what} not found; {hint}")
    if not nerfstudio_data:
        return
    if data.is_dir():
        transforms = data / "transforms.json"
        if not transforms.is_file():
            if config.data is None and data == Path("."):
                raise VoteSplatInputError(
                    f"no --data given and the current folder holds no transforms.json; {MAKE_DATASET_HINT}"
                )
            raise VoteSplatInputError(f"{where}: this folder holds no transforms.json; {MAKE_DATASET_HINT}")
    elif data.suffix == ".json":
        transforms = data
    else:
        raise VoteSplatInputError(
            f"{where} is a file, not a dataset; {MAKE_DATASET_HINT}, or that transforms.json itself"
        )
    try:
        meta = json.loads(transforms.read_text(encoding="utf-8"))
    except UnicodeDecodeError as err:
        raise VoteSplatInputError(
            f"{transforms} is not UTF-8 text (byte 0x{err.object[err.start]:02x} at position {err.start}); "
            "save it as UTF-8 (JSON's encoding), or make it again with ns-process-data"
        ) from None
    except json.JSONDecodeError as err:
        problem = "is empty" if not err.doc.strip() else f"is not valid JSON ({err})"
        raise VoteSplatInputError(f"{transforms} {problem}; fix it or make it again with ns-process-data") from None
    except OSError as err:  # unreadable (permissions), a folder named transforms.json, a symlink loop, ...
        raise VoteSplatInputError(
            f"{transforms} cannot be read ({err.strerror or err}); make it readable (e.g. chmod a+r), "
            "or copy the dataset somewhere you can read it"
        ) from None
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames or not all(isinstance(f, dict) and "file_path" in f for f in frames):
        raise VoteSplatInputError(
            f"{transforms} lists no frames (a 'frames' list whose entries have file_path and transform_matrix); "
            "make it again with ns-process-data"
        )
    if not check_images:
        return
    check_frames(transforms, meta, config, where, mask_source_flag)


CAMERA_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")


def _is_finite_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)


def _frame_name(number: int, frame: dict) -> str:
    return f"frame {number} ({frame['file_path']})"


def check_frames(
    transforms: Path,
    meta: dict,
    config: DataInput,
    where: str,
    mask_source_flag: str = "--pipeline.datamanager.mask-source",
) -> None:
    """Check every frame of a transforms.json before anything is trained or cached.

    One place for what would otherwise fail late, with a traceback, or silently: a pose or camera
    value that is not a finite number (sklearn's "Input X contains NaN" in splatfacto's set-up),
    the same image listed twice (trained double-weighted), mask paths on only some frames (the
    'auto' mask source would switch to SAM), image files that are missing, not images, or not the
    size the frame's camera says (later blamed on their masks). And what would train silently
    wrong: a camera model splatfacto would take for a pinhole (:func:`check_camera_model`), an image
    in a mode nerfstudio's loader reads as wrong colours (CMYK, palette), label images stored lossily
    (:func:`check_label_files`).
    """
    frames = meta["frames"]
    name = transforms.name
    remake = "or make the dataset again with ns-process-data"

    def check_camera_values(entry: dict, what: str) -> None:
        for key in CAMERA_KEYS:
            value = entry.get(key)
            if value is not None and not (_is_finite_number(value) and (value > 0 or key in ("cx", "cy"))):
                bound = "" if key in ("cx", "cy") else " > 0"
                raise VoteSplatInputError(
                    f"{transforms}: {what} has camera value {key}={value!r}; it must be a finite number{bound}; fix it, {remake}"
                )

    check_camera_values(meta, "the file")
    check_camera_model(transforms, meta)
    for number, frame in enumerate(frames):
        matrix = frame.get("transform_matrix")
        rows = np.asarray(matrix, dtype=object) if isinstance(matrix, list) else None
        if rows is None or rows.shape not in ((4, 4), (3, 4)) or not all(_is_finite_number(v) for v in rows.ravel()):
            problem = (
                "no transform_matrix"
                if matrix is None
                else "a transform_matrix that is not a 4x4 (or 3x4) grid of finite numbers"
            )
            raise VoteSplatInputError(
                f"{transforms}: {_frame_name(number, frame)} has {problem} (NaN/Inf in a pose usually means a camera "
                f"COLMAP failed to register); fix or remove that frame, {remake}"
            )
        check_camera_values(frame, _frame_name(number, frame))
    check_intrinsics_given(transforms, meta)
    check_camera_spread(transforms, frames)
    check_split_lists(transforms, meta)
    seen: Dict[str, int] = {}
    for number, frame in enumerate(frames):
        path = os.path.normpath(str(frame["file_path"]))
        if path in seen:
            raise VoteSplatInputError(
                f"{transforms}: frames {seen[path]} and {number} both list {frame['file_path']} (it would be trained twice as often); "
                "remove the duplicate frame"
            )
        seen[path] = number
    if config.mask_source in ("auto", "dataset"):
        levels = ("instance",) if config.mask_source == "auto" else (config.mask_levels or DATASET_LEVELS)
        for level in levels:
            key = f"{level}_mask_path"
            lacking = [number for number, frame in enumerate(frames) if key not in frame]
            if 0 < len(lacking) < len(frames) or (lacking and config.mask_source == "dataset"):
                first = lacking[0]
                raise VoteSplatInputError(
                    f"{transforms}: {len(lacking)} of {len(frames)} frames list no {key} (first: {_frame_name(first, frames[first])}); "
                    f"give every frame one, or make masks another way with {mask_source_flag} sam (or folder)"
                )

    if config.mask_source in ("auto", "dataset"):
        check_label_files(transforms, frames, config.mask_levels or DATASET_LEVELS)

    downscale_factor = config.dataparser.downscale_factor
    downscaled = downscale_factor is not None and downscale_factor > 1
    images = [frame_image_path(transforms.parent, frame["file_path"], downscale_factor) for frame in frames]
    missing = [image for image in images if not image.is_file()]
    if missing:
        if downscaled:
            fix = f"put the downscaled images in images_{downscale_factor}/ (--downscale-factor {downscale_factor})"
        else:
            fix = f"put the images where the file_path entries of {name} point"
        link = (
            f", a symbolic link to {os.readlink(missing[0])} that leads to no file" if missing[0].is_symlink() else ""
        )
        raise VoteSplatInputError(
            f"{where}: {len(missing)} of {len(images)} images listed in {name} are missing (first: {missing[0]}{link}); "
            f"{fix}, {remake}"
        )
    scale = float(downscale_factor) if downscale_factor is not None and downscaled else 1.0
    for number, (frame, image) in enumerate(zip(frames, images)):
        (actual_w, actual_h), mode, _ = image_file_header(image)
        if mode in ("I", "F") or mode.startswith("I;16"):
            raise VoteSplatInputError(
                f"image {image} is a {'float' if mode == 'F' else '16/32-bit'} single-channel image (PIL mode {mode}), "
                "which nerfstudio's image loader and SAM would read wrapped or clipped to 8 bits; save it as an 8-bit "
                "RGB or greyscale image"
            )
        if mode not in NERFSTUDIO_IMAGE_MODES:
            raise VoteSplatInputError(
                f"image {image} has PIL mode {mode}, which nerfstudio's image loader reads as wrong colours "
                f"(CMYK as inverted RGBA, palette indices as grey); convert it to RGB, or RGBA to keep transparency (e.g. PIL's "
                f"Image.open(path).convert('RGB').save(path))"
            )
        # nerfstudio's dataparser reads a top-level value for every frame, a frame's only without one
        width, height = meta.get("w", frame.get("w")), meta.get("h", frame.get("h"))
        if width is None or height is None:
            continue
        if abs(actual_w - width / scale) > 1 or abs(actual_h - height / scale) > 1:
            expected = f"{int(width // scale)}x{int(height // scale)}"
            raise VoteSplatInputError(
                f"image {image} is {actual_w}x{actual_h} but {name} gives its camera ({_frame_name(number, frame)}) as "
                f"{expected}{f' at --downscale-factor {downscale_factor}' if downscaled else ''}; "
                f"replace the image with one of the camera's size, or fix w/h and the intrinsics in {name}"
            )


def check_intrinsics_given(transforms: Path, meta: dict) -> None:
    """Every frame must get each camera value (fl_x, fl_y, cx, cy, w, h) from the file's top level or its own entry,
    and a frame's own value must agree with the top-level one, which nerfstudio's dataparser reads for every frame
    (the frame's is ignored: the camera would not be the one the frame says)."""
    frames = meta["frames"]
    remake = "or make the dataset again with ns-process-data"
    for key in CAMERA_KEYS:
        if key in meta:
            differing = [n for n, frame in enumerate(frames) if key in frame and frame[key] != meta[key]]
            if differing:
                first = differing[0]
                raise VoteSplatInputError(
                    f"{transforms}: {_frame_name(first, frames[first])} gives {key}={frames[first][key]!r} but the file "
                    f"gives {key}={meta[key]!r} for every frame ({len(differing)} frames differ), and nerfstudio reads "
                    f"only the file's; make them agree (or keep {key} in the frames only), {remake}"
                )
            continue
        lacking = [n for n, frame in enumerate(frames) if key not in frame]
        if lacking:
            first = lacking[0]
            raise VoteSplatInputError(
                f"{transforms}: no {key}, neither for the whole file nor for {_frame_name(first, frames[first])} "
                f"({len(lacking)} of {len(frames)} frames lack it); give {key} once at the top of {transforms.name} or "
                f"in every frame, {remake}"
            )


def check_camera_spread(transforms: Path, frames: list) -> None:
    """Refuse a dataset whose cameras all stand at one place (one frame, say): nerfstudio scales the scene by the
    cameras' spread, which would then be zero (a scale of millions, or NaN)."""
    positions = np.array([np.asarray(frame["transform_matrix"], dtype=np.float64)[:3, 3] for frame in frames])
    if len(frames) < 2 or float(np.ptp(positions, axis=0).max()) == 0.0:
        what = "lists one frame" if len(frames) < 2 else f"places all {len(frames)} cameras at one point"
        raise VoteSplatInputError(
            f"{transforms} {what}; a scene needs views from several places (nerfstudio scales the scene by how far "
            "the cameras spread): make the dataset from more images taken while moving around the scene"
        )


def check_split_lists(transforms: Path, meta: dict) -> None:
    """The ``train/val/test_filenames`` lists, when given, must name listed frames, and ns-train needs both the train
    and the val list (nerfstudio's dataparser raises for an unknown name or a missing list)."""
    given = [split for split in ("train", "val", "test") if f"{split}_filenames" in meta]
    if not given:
        return
    listed = {os.path.normpath(str(frame["file_path"])) for frame in meta["frames"]}
    for split in given:
        names = meta[f"{split}_filenames"]
        unknown = (
            [name for name in names if os.path.normpath(str(name)) not in listed]
            if isinstance(names, list)
            else [names]
        )
        if unknown:
            raise VoteSplatInputError(
                f"{transforms}: {split}_filenames lists {unknown[0]}{f' (and {len(unknown) - 1} more)' if len(unknown) > 1 else ''}, "
                f"which no frame lists; remove it from {split}_filenames or give it a frame"
            )
    missing = [split for split in ("train", "val") if split not in given]
    if missing:
        raise VoteSplatInputError(
            f"{transforms} gives {', '.join(f'{split}_filenames' for split in given)} but no {missing[0]}_filenames, "
            "which nerfstudio then needs too; give it, or remove the split lists to let nerfstudio split the frames"
        )


def check_label_files(transforms: Path, frames: list, levels: Tuple[str, ...]) -> None:
    """Refuse label images (``<level>_mask_path``) stored in a lossy format, by their header.

    Missing or broken label files are named later, by the mask source that reads them.
    """
    for frame in frames:
        for level in levels:
            relative = frame.get(f"{level}_mask_path")
            if not isinstance(relative, str):
                continue
            path = transforms.parent / relative
            if not path.is_file():
                continue
            try:
                _, _, file_format = image_file_header(path, "label image")
            except VoteSplatInputError:
                continue  # read (and named) by the mask source
            check_label_format(path, file_format)


# camera_model values (nerfstudio's CAMERA_MODEL_TO_TYPE) whose images splatfacto renders correctly:
# the pinhole models, with OpenCV's Brown distortion or the fisheye model undistorted by nerfstudio's
# full-image datamanager (and the vote labels warped the same way, see the vote datamanager).
SUPPORTED_CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "OPENCV_FISHEYE")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


def _distortion_params(entry: dict) -> list:
    """The [k1, k2, k3, k4, p1, p2] nerfstudio's dataparser reads from a transforms.json entry."""
    if "distortion_params" in entry:
        return list(entry["distortion_params"])
    return [entry.get(key, 0.0) for key in DISTORTION_KEYS]


def check_camera_model(transforms: Path, meta: dict) -> None:
    """Refuse cameras that would be trained as pinholes though their images are not.

    nerfstudio reads ``camera_model`` for the whole file. Splatfacto renders every camera as a
    pinhole; the full-image datamanager undistorts OPENCV and OPENCV_FISHEYE images first, but only
    when a distortion parameter is non-zero, so a fisheye file without k1..k4 would be taken for a
    pinhole one. Equirectangular, stereo, VR180, orthographic and FISHEYE624 images are not undistorted.
    """
    model = meta.get("camera_model", "OPENCV")
    supported = ", ".join(SUPPORTED_CAMERA_MODELS)
    if model not in SUPPORTED_CAMERA_MODELS:
        raise VoteSplatInputError(
            f"{transforms}: camera_model {model!r} is not supported (splatfacto would train it as a pinhole "
            f"camera); supported: {supported}; undistort the images to pinhole ones (e.g. COLMAP's image_undistorter)"
        )
    if model != "OPENCV_FISHEYE":
        return
    distort_fixed = any(key in meta for key in ("k1", "k2", "k3", "p1", "p2", "distortion_params"))
    for number, frame in enumerate(meta["frames"]):
        params = _distortion_params(meta if distort_fixed else frame)
        try:
            flat = np.asarray(params, dtype=np.float64).ravel()
        except (TypeError, ValueError):
            continue  # a malformed value is nerfstudio's dataparser's to report
        if not np.any(flat[:4]):
            raise VoteSplatInputError(
                f"{transforms}: camera_model OPENCV_FISHEYE with k1..k4 all 0 ({_frame_name(number, frame)}) would be "
                "trained as a pinhole camera (nerfstudio undistorts only non-zero distortion); give the fisheye's "
                "k1..k4, or undistort the images to pinhole ones and set camera_model PINHOLE"
            )
