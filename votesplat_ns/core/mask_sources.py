"""Where a view's masks come from: SAM, a folder of label PNGs, or the dataset's own label images.

Every source returns, per image, one integer label image per level (0 = no mask, k > 0 = mask k)
at the image's resolution or a uniformly scaled copy of it (the vote maps are resized to the
training resolution later). ``config_key()`` lists every argument that changes the output, and
``view_fingerprint()`` the per-view inputs other than the image itself (e.g. label files), so
that :mod:`votesplat_ns.core.vote_cache` can tell when cached votes are stale.

The interface is :class:`~votesplat_ns.core.mask_source_base.MaskSource`, the SAM source lives in
:mod:`votesplat_ns.core.sam_masks` and the file readers in :mod:`votesplat_ns.core.image_files`;
all of them are importable from here too.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import numpy as np

from votesplat_ns.core.image_files import (
    PathLike as PathLike,
    check_label_size as check_label_size,
    check_label_sizes_agree as check_label_sizes_agree,
    file_digest as file_digest,
    image_file_size as image_file_size,
    load_image_file as load_image_file,
    read_image_rgb as read_image_rgb,
    read_label_png as read_label_png,
)
from votesplat_ns.core.mask_source_base import MaskSource as MaskSource, validate_levels
from votesplat_ns.core.sam_masks import (
    SAM_CHECKPOINT_FILES as SAM_CHECKPOINT_FILES,
    SAM_LEVELS as SAM_LEVELS,
    SamMaskSource as SamMaskSource,
    check_sam_checkpoint as check_sam_checkpoint,
)
from votesplat_ns.errors import VoteSplatInputError


def _is_hidden_folder(name: str) -> bool:
    """Folders tools leave beside the data (.ipynb_checkpoints, .git, __pycache__): never a mask level."""
    return name.startswith(".") or name == "__pycache__"


# ------------------------------------------------------------------------ folder of label PNGs
class FolderMaskSource(MaskSource):
    """Precomputed masks: ``<root>/<level_name>/<image_stem>.png``.

    One single-channel 8- or 16-bit PNG label image per view and level (0 = no mask, k > 0 =
    mask k), the same size as the image (a uniformly scaled copy is accepted too). ``levels``
    defaults to the sub-folders of ``root`` in sorted order, leaving out hidden ones (``.name``,
    e.g. ``.ipynb_checkpoints``) and ``__pycache__``.
    """

    thread_safe = True  # reads label files only

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
        self.levels = validate_levels(levels, f"mask folder {self.root}")
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
        check_label_sizes_agree(
            [labels.shape for labels in label_images], [self.label_path(image_path, level) for level in self.levels]
        )
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

    thread_safe = True  # reads label files only

    def __init__(self, data: PathLike, levels: Sequence[str] = ("instance", "part")):
        data = Path(data)
        self.transforms_path = data if data.suffix == ".json" else data / "transforms.json"
        if not self.transforms_path.is_file():
            raise VoteSplatInputError(
                f"{self.transforms_path} does not exist; the 'dataset' mask source reads label paths from it"
            )
        self.root = self.transforms_path.parent
        self.levels = validate_levels(levels, "dataset mask source")
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
        check_label_sizes_agree([labels.shape for labels in label_images], [entry[level] for level in self.levels])
        return label_images

    def config_key(self) -> Dict[str, Any]:
        return {"type": "dataset", "levels": list(self.levels)}

    def view_fingerprint(self, image_path: PathLike, frame_index: int) -> str:
        entry = self._frame_for(image_path)
        return ";".join(
            f"{level}:{file_digest(entry[level]) if entry[level].is_file() else 'missing'}" for level in self.levels
        )


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
