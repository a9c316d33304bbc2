"""``votesplat masks``: make and cache a dataset's masks and 2D votes without training.

    votesplat masks --data <dataset> [--output-dir outputs] [--source auto|dataset|folder|sam ...] [--preview N]

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

import numpy as np

from votesplat_ns.core.vote_cache import VoteCache, VoteOptions, load_image_rgb
from votesplat_ns.core.vote_maps import DEFAULT_BORDER_MASKS
from votesplat_ns.core.vote_preview import render_vote_preview, write_png
from votesplat_ns.errors import VoteSplatInputError, writing_into
from votesplat_ns.ns.mask_settings import SamOptions

PREVIEW_FOLDER_NAME = "votesplat_previews"


@dataclass
class _MasksInput:
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


# SamOptions before _MasksInput in the bases: dataclass fields follow the reversed MRO, so the
# options keep their order (data first, then the SAM options, then these)
@dataclass
class MasksConfig(SamOptions, _MasksInput):
    """Precompute VoteSplat masks and 2D votes for a nerfstudio dataset."""

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


def make_masks(config: MasksConfig) -> Dict[str, object]:
    """Make all views' vote maps and the previews; returns where they went."""
    # the datamanager and its checks import nerfstudio, which `votesplat --help` should not wait for
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    from votesplat_ns.ns.data_checks import (
        check_cache_outside_dataset,
        check_data_input,
        dataset_dir,
        default_cache_dir,
    )
    from votesplat_ns.ns.datamanager import VoteDataManagerConfig

    if config.preview < 0:
        raise VoteSplatInputError(f"--preview must be >= 0, got {config.preview}")
    manager_config = VoteDataManagerConfig(
        data=config.data,
        mask_source=config.source,
        mask_levels=config.levels,
        mask_folder=config.mask_folder,
        border_masks=config.border_masks,
        dataparser=NerfstudioDataParserConfig(downscale_factor=config.downscale_factor),
        **config.sam_settings(),
    )
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
