"""votesplat-masks: make and cache a dataset's masks and 2D votes without training.

    votesplat-masks --data <dataset> [--output-dir outputs] [--source auto|dataset|folder|sam ...] [--preview N]

The cache goes where ``ns-train votesplat`` looks by default
(``<output-dir>/<dataset folder name>/votesplat_cache``), so training reuses it when run with
the same mask options and image downscale. ``--preview N`` saves, for N views spread over the
dataset, a PNG with one panel per mask level: masks in colour, centroids marked with a cross,
under ``<output-dir>/<dataset folder name>/votesplat_previews/``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple

import cv2
import numpy as np

from votesplat_ns.cli.cli_errors import VoteSplatInputError, one_line_errors, writing_into
from votesplat_ns.core.vote_cache import VoteCache, VoteOptions, atomic_write_bytes, load_image_rgb
from votesplat_ns.core.vote_maps import DEFAULT_BORDER_MASKS, VoteMaps

PREVIEW_FOLDER_NAME = "votesplat_previews"


@dataclass
class MasksConfig:
    """Precompute VoteSplat masks and 2D votes for a nerfstudio dataset."""

    data: Path
    """Dataset folder (with transforms.json) or the transforms.json file."""
    output_dir: Path = Path("outputs")
    """Same as ns-train's --output-dir: the cache goes to <output-dir>/<dataset name>/votesplat_cache."""
    cache_dir: Optional[Path] = None
    """Another cache folder (then give ns-train the same --pipeline.datamanager.cache-dir)."""
    source: Literal["auto", "dataset", "folder", "sam"] = "auto"
    """Mask source, as ns-train's --pipeline.datamanager.mask-source."""
    levels: Optional[Tuple[str, ...]] = None
    """Mask levels in order (default: depends on the source)."""
    mask_folder: Optional[Path] = None
    """For --source folder: a folder of <level>/<image file stem>.png label images."""
    sam_checkpoint: Optional[Path] = None
    """For --source sam: the SAM checkpoint file (never downloaded)."""
    sam_model_type: Literal["vit_h", "vit_l", "vit_b"] = "vit_h"
    """SAM backbone of that checkpoint."""
    sam_device: Optional[str] = None
    """Device SAM runs on (default: cuda when available, else cpu)."""
    sam_points_per_side: int = 32
    """SAM automatic mask generator: points per image side."""
    sam_pred_iou_thresh: float = 0.7
    """SAM automatic mask generator: lowest predicted IoU of a kept mask."""
    sam_stability_score_thresh: float = 0.85
    """SAM automatic mask generator: lowest stability score of a kept mask."""
    sam_crop_n_layers: int = 1
    """SAM automatic mask generator: layers of image crops (0: whole image only)."""
    sam_min_mask_region_area: int = 100
    """SAM automatic mask generator: smallest mask region kept, in pixels."""
    sam_max_long_side: Optional[int] = 1080
    """Images are shrunk to this long side before SAM (None: full size)."""
    border_masks: Literal["vote", "mask_only", "drop"] = DEFAULT_BORDER_MASKS
    """A mask touching the image border: vote, mask_only (no vote target) or drop, as ns-train's flag."""
    downscale_factor: Optional[int] = None
    """nerfstudio's --downscale-factor (images_N/); give training's for the cache to be reused."""
    preview: int = 0
    """Number of views to save a picture of the masks and centroids for."""


def dataset_images(data: Path, downscale_factor: Optional[int]) -> List[Path]:
    """The image files nerfstudio's dataparser reads for training and evaluation, in its order."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    parser = NerfstudioDataParserConfig(data=Path(data), downscale_factor=downscale_factor).setup()
    seen: Dict[Path, None] = {}
    for split in ("train", "val"):
        try:
            outputs = parser.get_dataparser_outputs(split=split)
        except RuntimeError:  # a dataset listing train_filenames but no val_filenames
            if split == "train":
                raise
            continue
        for path in outputs.image_filenames:
            seen.setdefault(Path(path), None)
    return list(seen)


def _label_colours(count: int) -> np.ndarray:
    """Distinct deterministic colours (golden-ratio hues), uint8 [count, 3]; row 0 black."""
    hues = (np.arange(count) * 0.61803398875) % 1.0
    hsv = np.stack([hues * 179, np.full(count, 200), np.full(count, 255)], axis=-1).astype(np.uint8)
    colours = cv2.cvtColor(hsv[None], cv2.COLOR_HSV2RGB)[0]
    colours[0] = 0
    return colours


def render_vote_preview(image: np.ndarray, vote_maps: VoteMaps) -> np.ndarray:
    """One panel per level, side by side: image with masks tinted and each centroid marked by a cross."""
    height, width = vote_maps.height, vote_maps.width
    if image.shape[:2] != (height, width):
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    marker = max(5, min(height, width) // 30)
    panels = []
    for level in range(vote_maps.num_levels):
        labels = np.asarray(vote_maps.labels[level]).astype(np.int64)
        table = vote_maps.centroids[level]
        colours = _label_colours(table.shape[0])
        inside = labels > 0
        panel = image.astype(np.float32)
        panel[inside] = 0.45 * panel[inside] + 0.55 * colours[labels[inside]]
        panel = np.ascontiguousarray(panel.clip(0, 255).astype(np.uint8))
        for k in range(1, table.shape[0]):
            if not np.all(np.isfinite(table[k])):
                continue
            centre = (int(round(float(table[k, 0]))), int(round(float(table[k, 1]))))
            cv2.drawMarker(panel, centre, (0, 0, 0), cv2.MARKER_CROSS, marker, 3)
            cv2.drawMarker(panel, centre, tuple(int(c) for c in colours[k]), cv2.MARKER_CROSS, marker, 1)
        if width >= 160:  # a caption would cover a tiny image
            name = vote_maps.level_names[level] if vote_maps.level_names else str(level)
            scale = width / 640
            origin = (4, 4 + int(24 * scale))
            text = f"{name}: {table.shape[0] - 1} masks"
            cv2.putText(panel, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), max(2, int(4 * scale)))
            cv2.putText(panel, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), max(1, int(1.5 * scale)))
        panels.append(panel)
        panels.append(np.full((height, 3, 3), 255, dtype=np.uint8))
    return np.concatenate(panels[:-1], axis=1)


def write_png(path: Path, image_rgb: np.ndarray) -> None:
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"could not encode preview {path}")
    atomic_write_bytes(path, lambda handle: handle.write(encoded.tobytes()))


def main(config: MasksConfig) -> Dict[str, object]:
    """Make all views' vote maps and the previews; returns where they went."""
    from votesplat_ns.ns.datamanager import (
        VoteDataManagerConfig,
        check_cache_outside_dataset,
        check_data_input,
        dataset_dir,
        default_cache_dir,
    )

    if config.preview < 0:
        raise VoteSplatInputError(f"--preview must be >= 0, got {config.preview}")
    manager_config = VoteDataManagerConfig(
        data=config.data,
        mask_source=config.source,
        mask_levels=config.levels,
        mask_folder=config.mask_folder,
        sam_checkpoint=config.sam_checkpoint,
        sam_model_type=config.sam_model_type,
        sam_device=config.sam_device,
        sam_points_per_side=config.sam_points_per_side,
        sam_pred_iou_thresh=config.sam_pred_iou_thresh,
        sam_stability_score_thresh=config.sam_stability_score_thresh,
        sam_crop_n_layers=config.sam_crop_n_layers,
        sam_min_mask_region_area=config.sam_min_mask_region_area,
        sam_max_long_side=config.sam_max_long_side,
        border_masks=config.border_masks,
    )
    manager_config.dataparser.downscale_factor = config.downscale_factor
    check_data_input(manager_config, where=f"--data {config.data}", mask_source_flag="--source")
    cache_dir = config.cache_dir if config.cache_dir is not None else default_cache_dir(config.data, config.output_dir)
    check_cache_outside_dataset(cache_dir, config.data)
    # the folder the user chose: --cache-dir, or --output-dir that holds the default cache folder
    folder, flag = (cache_dir, "--cache-dir") if config.cache_dir is not None else (config.output_dir, "--output-dir")
    source = manager_config.make_mask_source()
    images = dataset_images(config.data, config.downscale_factor)
    views = list(enumerate(images))
    with writing_into(folder, flag):
        cache = VoteCache(cache_dir, source, VoteOptions(border_masks=config.border_masks))
        keys = cache.build_all(views)
    print(f"vote maps of {len(views)} views ({source.name} masks, levels {list(source.levels)}) in {cache.entry_dir}")
    if cache.rebuilt_damaged:
        print(f"{cache.rebuilt_damaged} damaged cache entries were rebuilt")

    preview_paths: List[Path] = []
    if config.preview > 0 and views:
        preview_dir = cache_dir.parent / PREVIEW_FOLDER_NAME
        chosen = np.unique(np.linspace(0, len(views) - 1, num=min(config.preview, len(views))).round().astype(int))
        with writing_into(folder, flag):
            for i in chosen:
                index, image_path = views[int(i)]
                vote_maps = cache.load(keys[int(i)]) or cache.get(index, image_path)
                path = preview_dir / f"{Path(image_path).stem}.png"
                write_png(path, render_vote_preview(load_image_rgb(image_path), vote_maps))
                preview_paths.append(path)
        print(f"{len(preview_paths)} previews in {preview_dir}")
    return {"entry_dir": cache.entry_dir, "keys": keys, "previews": preview_paths, "dataset": dataset_dir(config.data)}


def entrypoint() -> None:
    import tyro

    config = tyro.cli(MasksConfig)
    with one_line_errors(prog="votesplat-masks"):
        main(config)


if __name__ == "__main__":
    entrypoint()
