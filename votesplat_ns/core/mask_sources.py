"""Where a view's masks come from: SAM, a folder of label PNGs, or the dataset's own label images.

Every source returns, per image, one integer label image per level (0 = no mask, k > 0 = mask k)
at the image's resolution or a uniformly scaled copy of it (the vote maps are resized to the
training resolution later). ``config_key()`` lists every argument that changes the output, and
``view_fingerprint()`` the per-view inputs other than the image itself (e.g. label files), so
that :mod:`votesplat_ns.core.vote_cache` can tell when cached votes are stale.
"""

from __future__ import annotations

import abc
import hashlib
import json
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
from PIL import Image, UnidentifiedImageError

from votesplat_ns.cli.cli_errors import VoteSplatInputError, load_failure_reason
from votesplat_ns.core.vote_maps import labels_from_binary_masks

PathLike = Union[str, Path]

SAM_CHECKPOINT_FILES = {
    "vit_h": "sam_vit_h_4b8939.pth",
    "vit_l": "sam_vit_l_0b3195.pth",
    "vit_b": "sam_vit_b_01ec64.pth",
}
"""File names of the official SAM checkpoints, as listed in the README of facebookresearch/segment-anything."""

SAM_LEVELS = ("default", "s", "m", "l")


def file_digest(path: PathLike, chunk_size: int = 1 << 20) -> str:
    """sha256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while True:
            chunk = handle.read(chunk_size)
            if not chunk:
                break
            digest.update(chunk)
    return digest.hexdigest()


def load_image_file(path: PathLike, what: str = "image") -> Image.Image:
    """An image file decoded in full by PIL; a missing, truncated or unreadable file raises a
    :class:`VoteSplatInputError` naming it (``what``: "image", "label image", ...).

    Every image and label file the plugin reads goes through here (nerfstudio's own image loading
    is checked with it too, see the datamanager), so a broken file is always named.
    """
    path = Path(path)
    if not path.is_file():
        raise VoteSplatInputError(f"{what} {path} does not exist")
    try:
        with Image.open(path) as image:
            image.load()
    except Exception as error:  # PIL raises OSError, ValueError, SyntaxError, ... for broken files
        text = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        if isinstance(error, UnidentifiedImageError):
            text = "not an image format PIL can read"
        elif "truncated" in text or isinstance(error, EOFError):
            text = f"the file is truncated: {text}"
        raise VoteSplatInputError(f"{what} {path} cannot be read ({text}); replace it with an intact file") from None
    return image


def image_file_size(path: PathLike, what: str = "image") -> Tuple[int, int]:
    """``(width, height)`` from an image file's header (nothing decoded); an unreadable file raises a named error."""
    path = Path(path)
    try:
        with Image.open(path) as image:
            return image.size
    except FileNotFoundError:
        raise VoteSplatInputError(f"{what} {path} does not exist") from None
    except Exception:  # not an image, or a header PIL cannot parse: load_image_file says which
        load_image_file(path, what)
        raise


def read_image_rgb(path: PathLike, what: str = "image") -> np.ndarray:
    """An image file's pixels as uint8 [H, W, 3] (alpha dropped, grey expanded); errors name the file."""
    return np.asarray(load_image_file(path, what).convert("RGB"))


def read_label_png(path: PathLike) -> np.ndarray:
    """Read a single-channel 8- or 16-bit label PNG as int32 [H, W]."""
    path = Path(path)
    image = load_image_file(path, "label image")
    mode = image.mode
    labels = np.array(image)
    if labels.ndim != 2 or mode not in ("L", "P", "I", "I;16", "I;16B", "I;16L"):
        raise VoteSplatInputError(
            f"label image {path} has mode {mode} with shape {labels.shape}; it must be a single-channel "
            "8- or 16-bit PNG holding mask ids (0 = no mask)"
        )
    labels = labels.astype(np.int32)
    if labels.size and labels.min() < 0:
        raise VoteSplatInputError(f"label image {path} holds negative ids; use 0 for no mask and 1..K for masks")
    return labels


def check_label_size(label_hw: Tuple[int, int], image_hw: Tuple[int, int], what: str) -> None:
    """Accept a label image of the image's size, or a uniformly scaled copy (to within a pixel).

    The scaled case covers nerfstudio reading downscaled images (``images_2/``) while the label
    images stay at full resolution.
    """
    label_h, label_w = (int(v) for v in label_hw)
    image_h, image_w = (int(v) for v in image_hw)
    if (label_h, label_w) == (image_h, image_w):
        return
    if min(label_h, label_w, image_h, image_w) > 0:
        # predicted image height/width if the label image were the image scaled uniformly
        height_from_width = label_h * image_w / label_w
        width_from_height = label_w * image_h / label_h
        if abs(height_from_width - image_h) <= 1.0 and abs(width_from_height - image_w) <= 1.0:
            return
    raise VoteSplatInputError(
        f"{what} is {label_w}x{label_h} but its image is {image_w}x{image_h}; "
        "label images must have the image's size (or be a uniformly scaled copy of it)"
    )


class MaskSource(abc.ABC):
    """Makes one label image per level for an image."""

    levels: Tuple[str, ...]

    @abc.abstractmethod
    def masks_for_image(self, image: np.ndarray, image_path: PathLike, frame_index: int) -> List[np.ndarray]:
        """Label images (integer [h, w], one per level in ``self.levels``) for one view.

        Args:
            image: uint8 [H, W, 3], the pixels of ``image_path``.
            image_path: the image file the pixels came from.
            frame_index: the view's index in the caller's list of views (informational).
        """

    @abc.abstractmethod
    def config_key(self) -> Dict[str, Any]:
        """JSON-serialisable description of every argument that affects the output."""

    def view_fingerprint(self, image_path: PathLike, frame_index: int) -> str:
        """Digest of the per-view inputs other than the image pixels (default: none)."""
        return ""

    @property
    def name(self) -> str:
        return str(self.config_key()["type"])


def _is_hidden_folder(name: str) -> bool:
    """Folders tools leave beside the data (.ipynb_checkpoints, .git, __pycache__): never a mask level."""
    return name.startswith(".") or name == "__pycache__"


def _validate_levels(levels: Sequence[str], what: str) -> Tuple[str, ...]:
    levels = tuple(str(level) for level in levels)
    if not levels:
        raise VoteSplatInputError(f"{what}: give at least one mask level")
    if len(set(levels)) != len(levels):
        raise VoteSplatInputError(f"{what}: mask levels {levels} contain duplicates")
    return levels


# ------------------------------------------------------------------------ folder of label PNGs
class FolderMaskSource(MaskSource):
    """Precomputed masks: ``<root>/<level_name>/<image_stem>.png``.

    One single-channel 8- or 16-bit PNG label image per view and level (0 = no mask, k > 0 =
    mask k), the same size as the image (a uniformly scaled copy is accepted too). ``levels``
    defaults to the sub-folders of ``root`` in sorted order, leaving out hidden ones (``.name``,
    e.g. ``.ipynb_checkpoints``) and ``__pycache__``.
    """

    def __init__(self, root: PathLike, levels: Optional[Sequence[str]] = None):
        self.root = Path(root)
        if not self.root.is_dir():
            raise VoteSplatInputError(
                f"mask folder {self.root} does not exist; it must hold one sub-folder of label PNGs per level"
            )
        if levels is None:
            levels = sorted(p.name for p in self.root.iterdir() if p.is_dir() and not _is_hidden_folder(p.name))
            if not levels:
                raise VoteSplatInputError(
                    f"mask folder {self.root} has no level sub-folders (expected <root>/<level>/<image_stem>.png)"
                )
        self.levels = _validate_levels(levels, f"mask folder {self.root}")
        for level in self.levels:
            if not (self.root / level).is_dir():
                raise VoteSplatInputError(
                    f"mask folder {self.root} has no sub-folder '{level}' for level '{level}' "
                    f"(levels {list(self.levels)} need one folder each)"
                )

    def label_path(self, image_path: PathLike, level: str) -> Path:
        return self.root / level / f"{Path(image_path).stem}.png"

    def masks_for_image(self, image: np.ndarray, image_path: PathLike, frame_index: int) -> List[np.ndarray]:
        label_images = []
        for level in self.levels:
            path = self.label_path(image_path, level)
            if not path.is_file():
                raise VoteSplatInputError(
                    f"missing label image {path} for image {Path(image_path).name} at level '{level}' "
                    f"(every level in {list(self.levels)} needs one PNG per image)"
                )
            labels = read_label_png(path)
            check_label_size(labels.shape, image.shape[:2], f"label image {path}")
            label_images.append(labels)
        return label_images

    def config_key(self) -> Dict[str, Any]:
        return {"type": "folder", "levels": list(self.levels)}

    def view_fingerprint(self, image_path: PathLike, frame_index: int) -> str:
        parts = []
        for level in self.levels:
            path = self.label_path(image_path, level)
            parts.append(f"{level}:{file_digest(path) if path.is_file() else 'missing'}")
        return ";".join(parts)


# ------------------------------------------------------------- the dataset's own label images
class DatasetMaskSource(MaskSource):
    """Label images listed per frame in transforms.json as ``"<level>_mask_path"``.

    The synthetic scenes store ``"instance_mask_path"`` and ``"part_mask_path"``: 16-bit PNG
    label images relative to the dataset root, 0 = background. An image is matched to its frame
    by path, or by file name when nerfstudio reads a downscaled copy (``images_2/<name>``).
    """

    def __init__(self, data: PathLike, levels: Sequence[str] = ("instance", "part")):
        data = Path(data)
        self.transforms_path = data if data.suffix == ".json" else data / "transforms.json"
        if not self.transforms_path.is_file():
            raise VoteSplatInputError(
                f"{self.transforms_path} does not exist; the 'dataset' mask source reads label paths from it"
            )
        self.root = self.transforms_path.parent
        self.levels = _validate_levels(levels, "dataset mask source")
        with open(self.transforms_path, encoding="utf-8") as handle:
            meta = json.load(handle)
        frames = meta.get("frames", [])
        self._by_path: Dict[Path, Dict[str, Path]] = {}
        self._by_name: Dict[str, List[Dict[str, Path]]] = {}
        for number, frame in enumerate(frames):
            entry: Dict[str, Path] = {}
            for level in self.levels:
                key = f"{level}_mask_path"
                if key not in frame:
                    raise VoteSplatInputError(
                        f"frame {number} ({frame.get('file_path')}) of {self.transforms_path} has no '{key}'; "
                        "every frame needs one label image per level (or pick another --mask-source)"
                    )
                entry[level] = self.root / frame[key]
            image_path = (self.root / frame["file_path"]).resolve()
            self._by_path[image_path] = entry
            self._by_name.setdefault(image_path.name, []).append(entry)

    @staticmethod
    def has_masks(data: PathLike, level: str = "instance") -> bool:
        """Whether the dataset's transforms.json lists ``<level>_mask_path`` for its frames."""
        data = Path(data)
        path = data if data.suffix == ".json" else data / "transforms.json"
        if not path.is_file():
            return False
        with open(path, encoding="utf-8") as handle:
            frames = json.load(handle).get("frames", [])
        return bool(frames) and all(f"{level}_mask_path" in frame for frame in frames)

    def _frame_for(self, image_path: PathLike) -> Dict[str, Path]:
        resolved = Path(image_path).resolve()
        if resolved in self._by_path:
            return self._by_path[resolved]
        candidates = self._by_name.get(resolved.name, [])
        if len(candidates) == 1:
            return candidates[0]
        if not candidates:
            raise VoteSplatInputError(f"image {image_path} is not a frame of {self.transforms_path}")
        raise VoteSplatInputError(
            f"image {image_path} matches {len(candidates)} frames of {self.transforms_path} by file name; "
            "frame file names must be unique"
        )

    def masks_for_image(self, image: np.ndarray, image_path: PathLike, frame_index: int) -> List[np.ndarray]:
        entry = self._frame_for(image_path)
        label_images = []
        for level in self.levels:
            labels = read_label_png(entry[level])
            check_label_size(labels.shape, image.shape[:2], f"label image {entry[level]}")
            label_images.append(labels)
        return label_images

    def config_key(self) -> Dict[str, Any]:
        return {"type": "dataset", "levels": list(self.levels)}

    def view_fingerprint(self, image_path: PathLike, frame_index: int) -> str:
        entry = self._frame_for(image_path)
        return ";".join(
            f"{level}:{file_digest(entry[level]) if entry[level].is_file() else 'missing'}" for level in self.levels
        )


# ------------------------------------------------------------------------------------- SAM
class _OneGranularityPredictor:
    """A SamPredictor whose ``predict_torch`` keeps one of SAM's three multimask outputs.

    SAM answers a point prompt with three masks; ordered by output index they are, empirically,
    subpart, part and whole. Running segment_anything's unmodified automatic mask generator
    once per output index gives masks of one granularity per run, with its NMS acting within
    that granularity only. Image embeddings are computed once per (crop) image and reused
    across the runs, so the encoder cost is paid once.
    ``output_index = None`` keeps all three (the standard generator).
    """

    _STATE = ("features", "original_size", "input_size", "is_image_set")

    def __init__(self, predictor: Any):
        self._predictor = predictor
        self.output_index: Optional[int] = None
        self._embeddings: Dict[str, Dict[str, Any]] = {}

    def set_image(self, image: np.ndarray, image_format: str = "RGB") -> None:
        key = f"{image.shape}:{image_format}:{hashlib.sha1(np.ascontiguousarray(image).tobytes()).hexdigest()}"
        saved = self._embeddings.get(key)
        if saved is None:
            self._predictor.set_image(image, image_format)
            self._embeddings[key] = {name: getattr(self._predictor, name) for name in self._STATE}
        else:
            for name, value in saved.items():
                setattr(self._predictor, name, value)

    def clear_embeddings(self) -> None:
        self._embeddings.clear()
        self._predictor.reset_image()

    def predict_torch(
        self, point_coords, point_labels, boxes=None, mask_input=None, multimask_output=True, return_logits=False
    ):
        masks, iou_predictions, low_res = self._predictor.predict_torch(
            point_coords,
            point_labels,
            boxes,
            mask_input,
            multimask_output=multimask_output,
            return_logits=return_logits,
        )
        if self.output_index is None or not multimask_output:
            return masks, iou_predictions, low_res
        i = self.output_index
        return masks[:, i : i + 1], iou_predictions[:, i : i + 1], low_res[:, i : i + 1]

    def __getattr__(self, name: str) -> Any:
        return getattr(self._predictor, name)


class SamMaskSource(MaskSource):
    """Segment Anything's automatic mask generator, LangSplat-style hierarchical levels.

    Levels (any subset, in any order, of ``("default", "s", "m", "l")``):
      - ``"s"``, ``"m"``, ``"l"``: masks from SAM's multimask output 0, 1, 2 (subpart, part,
        whole), one generator run per output so that NMS only compares masks of one
        granularity (LangSplat's modified generator likewise keeps the three apart);
      - ``"default"``: the standard generator run over all three outputs together.
    Each level's masks are merged with :func:`labels_from_binary_masks` (smaller mask wins).
    LangSplat additionally removes redundant masks by score/inner-overlap; that step is not done.

    The generator defaults are LangSplat's (points_per_side=32, pred_iou_thresh=0.7,
    box_nms_thresh=0.7, stability_score_thresh=0.85, crop_n_layers=1, min_mask_region_area=100).
    Images whose long side exceeds ``max_long_side`` are downscaled before SAM (masks come back
    at that size; the vote maps are resized to the training resolution later).

    The checkpoint is never downloaded. Tests may pass ``sam_model`` (an already-built ``Sam``).
    """

    def __init__(
        self,
        checkpoint: Optional[PathLike] = None,
        model_type: str = "vit_h",
        device: Optional[str] = None,
        levels: Sequence[str] = SAM_LEVELS,
        points_per_side: int = 32,
        points_per_batch: int = 64,
        pred_iou_thresh: float = 0.7,
        stability_score_thresh: float = 0.85,
        box_nms_thresh: float = 0.7,
        crop_n_layers: int = 1,
        crop_n_points_downscale_factor: int = 1,
        min_mask_region_area: int = 100,
        max_long_side: Optional[int] = 1080,
        sam_model: Any = None,
    ):
        if model_type not in SAM_CHECKPOINT_FILES:
            raise VoteSplatInputError(
                f"unknown SAM model type '{model_type}'; use one of {sorted(SAM_CHECKPOINT_FILES)}"
            )
        self.levels = _validate_levels(levels, "SAM mask source")
        unknown = [level for level in self.levels if level not in SAM_LEVELS]
        if unknown:
            raise VoteSplatInputError(f"unknown SAM mask levels {unknown}; use a subset of {list(SAM_LEVELS)}")
        if max_long_side is not None and max_long_side < 16:
            raise VoteSplatInputError(f"max_long_side={max_long_side} is too small; use >= 16 or None")
        self.model_type = model_type
        self.device = device
        self.max_long_side = max_long_side
        self.generator_kwargs = dict(
            points_per_side=int(points_per_side),
            points_per_batch=int(points_per_batch),
            pred_iou_thresh=float(pred_iou_thresh),
            stability_score_thresh=float(stability_score_thresh),
            box_nms_thresh=float(box_nms_thresh),
            crop_n_layers=int(crop_n_layers),
            crop_n_points_downscale_factor=int(crop_n_points_downscale_factor),
            min_mask_region_area=int(min_mask_region_area),
        )
        self._sam_model = sam_model
        self._generator = None
        if sam_model is not None:
            self.checkpoint = None
            self._model_identity = {"model": "in-memory", "parameters_sha256": _state_dict_digest(sam_model)}
        else:
            self.checkpoint = check_sam_checkpoint(checkpoint, model_type)
            self._model_identity = {
                "model": model_type,
                "checkpoint_name": self.checkpoint.name,
                "checkpoint_bytes": self.checkpoint.stat().st_size,
                "checkpoint_sample_sha256": _sampled_digest(self.checkpoint),
            }

    def config_key(self) -> Dict[str, Any]:
        return {
            "type": "sam",
            "levels": list(self.levels),
            "max_long_side": self.max_long_side,
            **self._model_identity,
            **self.generator_kwargs,
        }

    def _resolve_device(self) -> str:
        if self.device:
            return self.device
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"

    def _build_generator(self):
        import torch
        from segment_anything import SamAutomaticMaskGenerator, sam_model_registry

        if self._sam_model is None:
            try:
                # loaded before the model is built, so a wrong file fails fast
                state_dict = torch.load(self.checkpoint, map_location="cpu", weights_only=True)
                model = sam_model_registry[self.model_type](checkpoint=None)
                model.load_state_dict(state_dict)
            except Exception as error:
                raise VoteSplatInputError(
                    f"could not load SAM checkpoint {self.checkpoint} as model type '{self.model_type}' ({load_failure_reason(error, self.checkpoint)}); "
                    f"expected the official {SAM_CHECKPOINT_FILES[self.model_type]} from the segment-anything "
                    "repository's README (facebookresearch/segment-anything)"
                ) from error
            self._sam_model = model
        self._sam_model.to(self._resolve_device()).eval()
        generator = _empty_safe_generator_class(SamAutomaticMaskGenerator)(
            self._sam_model, output_mode="uncompressed_rle", **self.generator_kwargs
        )
        generator.predictor = _OneGranularityPredictor(generator.predictor)
        return generator

    def masks_for_image(self, image: np.ndarray, image_path: PathLike, frame_index: int) -> List[np.ndarray]:
        from segment_anything.utils.amg import rle_to_mask

        image = _as_rgb_uint8(image, image_path)
        if self._generator is None:
            self._generator = self._build_generator()
        image = _limit_long_side(image, self.max_long_side)
        predictor: _OneGranularityPredictor = self._generator.predictor
        output_index = {"default": None, "s": 0, "m": 1, "l": 2}
        label_images = []
        try:
            for level in self.levels:
                predictor.output_index = output_index[level]
                annotations = self._generator.generate(image)
                label_images.append(_paint_rles(annotations, image.shape[:2], rle_to_mask))
        finally:
            predictor.output_index = None
            predictor.clear_embeddings()
        return label_images


def _empty_safe_generator_class(base: type) -> type:
    """segment_anything 1.0's generator with crops (crop_n_layers >= 1) crashes in its cross-crop NMS
    (``box_area`` of an empty 1-D tensor) when no crop yields a mask; a view without masks is valid
    (no vote supervision there), so this subclass returns no masks instead. Otherwise unchanged."""

    class EmptySafeMaskGenerator(base):
        def _generate_masks(self, image: np.ndarray):
            # SamAutomaticMaskGenerator._generate_masks of segment_anything 1.0, plus the empty guard
            import torch
            from segment_anything.utils.amg import MaskData, generate_crop_boxes
            from torchvision.ops.boxes import batched_nms, box_area

            orig_size = image.shape[:2]
            crop_boxes, layer_idxs = generate_crop_boxes(orig_size, self.crop_n_layers, self.crop_overlap_ratio)
            data = MaskData()
            for crop_box, layer_idx in zip(crop_boxes, layer_idxs):
                data.cat(self._process_crop(image, crop_box, layer_idx, orig_size))
            if len(crop_boxes) > 1 and len(data["rles"]) > 0:
                # remove duplicates between crops, preferring masks from smaller crops
                scores = 1 / box_area(data["crop_boxes"])
                scores = scores.to(data["boxes"].device)
                keep_by_nms = batched_nms(
                    data["boxes"].float(), scores, torch.zeros(len(data["boxes"])), iou_threshold=self.crop_nms_thresh
                )
                data.filter(keep_by_nms)
            data.to_numpy()
            return data

    return EmptySafeMaskGenerator


def _paint_rles(annotations: List[Dict[str, Any]], shape: Tuple[int, int], rle_to_mask) -> np.ndarray:
    """Label image from RLE masks with the rule of :func:`labels_from_binary_masks`, one mask in memory at a time."""
    if not annotations:
        return labels_from_binary_masks([], shape=shape)
    areas = np.array([int(a["area"]) for a in annotations], dtype=np.int64)
    indices = np.arange(len(annotations))
    labels = np.zeros(shape, dtype=np.int32)
    for i in np.lexsort((-indices, -areas)):
        labels[rle_to_mask(annotations[i]["segmentation"])] = i + 1
    return labels


def _as_rgb_uint8(image: np.ndarray, image_path: PathLike) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] not in (3, 4):
        raise VoteSplatInputError(f"image {image_path} must be uint8 [H, W, 3], got {image.dtype} {tuple(image.shape)}")
    return np.ascontiguousarray(image[..., :3])


def _limit_long_side(image: np.ndarray, max_long_side: Optional[int]) -> np.ndarray:
    height, width = image.shape[:2]
    if max_long_side is None or max(height, width) <= max_long_side:
        return image
    scale = max_long_side / max(height, width)
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    return np.asarray(Image.fromarray(image).resize(size, resample=Image.Resampling.BILINEAR))


def check_sam_checkpoint(checkpoint: Optional[PathLike], model_type: str) -> Path:
    """The checkpoint path if it is a readable file, else a one-line ValueError naming the expected file."""
    expected = SAM_CHECKPOINT_FILES[model_type]
    hint = (
        f"expected the SAM {model_type} checkpoint file {expected} (the official checkpoints are listed in the "
        "segment-anything repository's README, facebookresearch/segment-anything); it is never downloaded automatically"
    )
    if checkpoint is None or str(checkpoint) == "":
        raise VoteSplatInputError(f"no SAM checkpoint given: pass the path to {expected}; {hint}")
    path = Path(checkpoint).expanduser()
    if not path.is_file():
        raise VoteSplatInputError(f"SAM checkpoint {path} does not exist; {hint}")
    try:
        with open(path, "rb") as handle:
            handle.read(1)
    except OSError as error:
        raise VoteSplatInputError(f"SAM checkpoint {path} is not readable ({error.strerror}); {hint}") from error
    return path


def _sampled_digest(path: Path, sample: int = 1 << 20) -> str:
    """sha256 of a large file's size, first and last MiB (cheap identity for multi-GB checkpoints)."""
    size = path.stat().st_size
    digest = hashlib.sha256(str(size).encode())
    with open(path, "rb") as handle:
        digest.update(handle.read(sample))
        if size > sample:
            handle.seek(max(sample, size - sample))
            digest.update(handle.read(sample))
    return digest.hexdigest()


def _state_dict_digest(model: Any) -> str:
    digest = hashlib.sha256()
    for name, tensor in sorted(model.state_dict().items()):
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def make_mask_source(
    kind: str,
    data: Optional[PathLike] = None,
    levels: Optional[Sequence[str]] = None,
    mask_folder: Optional[PathLike] = None,
    sam_checkpoint: Optional[PathLike] = None,
    sam_model_type: str = "vit_h",
    sam_device: Optional[str] = None,
    sam_options: Optional[Dict[str, Any]] = None,
) -> MaskSource:
    """Build a mask source by name: "dataset", "folder", "sam" or "auto".

    "auto" picks "dataset" when the dataset's transforms.json lists ``instance_mask_path`` for
    every frame, else "sam".
    """
    if kind == "auto":
        if data is None:
            raise VoteSplatInputError("mask source 'auto' needs the dataset path")
        kind = "dataset" if DatasetMaskSource.has_masks(data) else "sam"
    if kind == "dataset":
        if data is None:
            raise VoteSplatInputError("mask source 'dataset' needs the dataset path")
        return DatasetMaskSource(data, levels=tuple(levels) if levels else ("instance", "part"))
    if kind == "folder":
        if mask_folder is None:
            raise VoteSplatInputError(
                "mask source 'folder' needs a mask folder: pass --mask-folder <root> (<root>/<level>/<image_stem>.png)"
            )
        return FolderMaskSource(mask_folder, levels=tuple(levels) if levels else None)
    if kind == "sam":
        return SamMaskSource(
            checkpoint=sam_checkpoint,
            model_type=sam_model_type,
            device=sam_device,
            levels=tuple(levels) if levels else SAM_LEVELS,
            **(sam_options or {}),
        )
    raise VoteSplatInputError(f"unknown mask source '{kind}'; use one of: auto, dataset, folder, sam")
