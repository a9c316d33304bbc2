"""``votesplat masks``: make and cache a dataset's masks and 2D votes without training.

    votesplat masks --data <dataset> [--output-dir outputs] [--source auto|dataset|folder|sam ...] [--preview N]
    votesplat masks --data <dataset> --num-gpus 4                      # one process per GPU, one cache
    torchrun --standalone --nproc-per-node 4 $(which votesplat) masks --data <dataset>   # the same, ranks by torchrun

The cache goes where ``ns-train votesplat`` looks by default
(``<output-dir>/<dataset folder name>/votesplat_cache``), so training reuses it when run with
the same mask options and image downscale. ``--preview N`` saves, for N views spread over the
dataset, a PNG with one panel per mask level: masks in colour, centroids marked with a cross,
under ``<output-dir>/<dataset folder name>/votesplat_previews/``.

With ``--num-gpus N`` rank r runs on GPU r (rank 0 in this process, ranks 1 .. N-1 in processes it starts) and
takes the next images not yet made (four, two at a time) whenever it is free; N ranks started by ``torchrun``
make the images r, r + N, ... each. All write the one cache (:mod:`votesplat_ns.core.vote_cache_ranks`); the
entries are those one process makes. ``--sam-device cpu`` runs the N ranks on the CPU instead.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Dict, List, Literal, Optional, Sequence, Tuple

import numpy as np
import torch

from votesplat_ns.core.sam_masks import check_sam_device
from votesplat_ns.core.vote_cache import VoteCache, VoteOptions, load_image_rgb
from votesplat_ns.core.vote_cache_ranks import build_on_ranks, rank_share
from votesplat_ns.core.vote_maps import DEFAULT_BORDER_MASKS
from votesplat_ns.core.vote_preview import render_vote_preview, write_png
from votesplat_ns.errors import VoteSplatInputError, check_writable_folder, writing_into
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
    num_gpus: int = 1
    """Processes making the masks, one per GPU (rank r on cuda:r takes the next image whenever it is free), all into one cache; with --sam-device cpu, N CPU processes. Under torchrun leave it at 1."""
    processes_per_gpu: int = 1
    """Processes making the masks on each GPU (of --num-gpus, or --sam-device's): each loads SAM, and does its host work (filters, small regions, labels) beside the others' instead of in one Python interpreter. Under torchrun leave it at 1."""


# a rank started by torchrun may wait this long at the end for the slowest rank
RANKS_TIMEOUT = timedelta(days=1)


def rank_devices(num_gpus: int, sam_device: Optional[str], processes_per_gpu: int = 1) -> List[str]:
    """The devices of the ranks of ``--num-gpus`` and ``--processes-per-gpu`` (one line when this machine lacks
    them): cuda:0..N-1, each K times, or N times cpu with ``--sam-device cpu``; [] for one process (it runs on
    ``--sam-device``). One GPU named by ``--sam-device`` takes the K processes of ``--num-gpus 1``."""
    if num_gpus < 1:
        raise VoteSplatInputError(f"--num-gpus {num_gpus}: give 1 or more processes")
    if processes_per_gpu < 1:
        raise VoteSplatInputError(f"--processes-per-gpu {processes_per_gpu}: give 1 or more processes per GPU")
    if sam_device == "cpu":
        if processes_per_gpu > 1:
            raise VoteSplatInputError(
                f"--processes-per-gpu {processes_per_gpu} shares a GPU, and --sam-device cpu runs on the CPU: "
                "leave --processes-per-gpu at 1 (--num-gpus N runs N CPU processes)"
            )
        return ["cpu"] * num_gpus if num_gpus > 1 else []
    if num_gpus == 1 and processes_per_gpu == 1:
        return []
    available = torch.cuda.device_count() if torch.cuda.is_available() else 0
    have = f"{available} GPU{'s' if available != 1 else ''}" + (" (CUDA is not available)" if not available else "")
    if sam_device not in (None, "cuda"):
        if num_gpus > 1:
            raise VoteSplatInputError(
                f"--num-gpus {num_gpus} runs rank r on cuda:r, but --sam-device {sam_device} names one device: "
                f"leave --sam-device out, or give --sam-device cpu for {num_gpus} CPU processes"
            )
        check_sam_device(sam_device)
        if torch.device(sam_device).type != "cuda":
            raise VoteSplatInputError(
                f"--processes-per-gpu {processes_per_gpu} shares a CUDA GPU, and --sam-device {sam_device} is not "
                "one: give --sam-device cuda:<index>, or leave --processes-per-gpu at 1"
            )
        return [sam_device] * processes_per_gpu
    if num_gpus > available:
        if processes_per_gpu > 1:
            fix = f"give --num-gpus {available} or less" if available else "leave --processes-per-gpu at 1"
            raise VoteSplatInputError(
                f"--num-gpus {num_gpus} --processes-per-gpu {processes_per_gpu}: this machine has {have}; {fix}"
            )
        raise VoteSplatInputError(
            f"--num-gpus {num_gpus}: this machine has {have}; give --num-gpus {max(1, available)} or less, "
            f"or add --sam-device cpu to run {num_gpus} CPU processes"
        )
    # rank 0 (this process) on cuda:0, and each GPU's processes spread over the ranks
    return [f"cuda:{rank % num_gpus}" for rank in range(num_gpus * processes_per_gpu)]


def launcher_rank() -> Optional[Tuple[int, int, int]]:
    """(rank, world size, local rank) when a launcher (torchrun) started this process as one of several ranks."""
    world = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if world <= 1 or "RANK" not in os.environ:
        return None
    rank = int(os.environ["RANK"])
    return rank, world, int(os.environ.get("LOCAL_RANK", rank))


def _launched_rank_device(local_rank: int, sam_device: Optional[str]) -> str:
    if sam_device == "cpu":
        return "cpu"
    available = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if local_rank >= available:
        raise VoteSplatInputError(
            f"torchrun started local rank {local_rank}, but this machine has {available} GPU(s): start at most "
            f"{available} processes per node (--nproc-per-node), or give --sam-device cpu"
        )
    return f"cuda:{local_rank}"


def _build_as_launched_rank(
    cache: VoteCache, views: Sequence[Tuple[int, Path]], keys: List[str], ranks: Tuple[int, int, int], sam_device
) -> None:
    """This process's share of the cache as rank ``ranks[0]`` of ``ranks[1]`` (torchrun), then wait for all ranks."""
    import torch.distributed as dist

    rank, world, local_rank = ranks
    device = _launched_rank_device(local_rank, sam_device)
    if device.startswith("cuda"):
        torch.cuda.set_device(torch.device(device))
    else:
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // int(os.environ.get("LOCAL_WORLD_SIZE", world))))
    own = VoteCache(cache.entry_dir.parent, cache.source.on_device(device), cache.vote_options)
    dist.init_process_group("gloo", timeout=RANKS_TIMEOUT)  # only a barrier: gloo serves CPU and GPU ranks
    try:
        own.build_all(
            rank_share(views, rank, world),
            keys=rank_share(keys, rank, world),
            progress=rank == 0,
            description=f"Making vote maps ({cache.source.name} masks; rank 0's share of {world})",
        )
        dist.barrier()
    finally:
        dist.destroy_process_group()


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
    devices = rank_devices(config.num_gpus, config.sam_device, config.processes_per_gpu)
    launched = launcher_rank()
    if launched is not None and devices:
        flags = f"--num-gpus {config.num_gpus}" + (
            f" --processes-per-gpu {config.processes_per_gpu}" if config.processes_per_gpu > 1 else ""
        )
        raise VoteSplatInputError(
            f"{flags} starts its own processes, and torchrun started this one as rank "
            f"{launched[0]} of {launched[1]}: use one of the two (under torchrun leave --num-gpus and "
            "--processes-per-gpu at 1)"
        )
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
        keys = [cache.view_key(path, index) for index, path in views]
        missing = sum(1 for key in keys if not cache.votes_path(key).is_file())
        if missing and (devices or launched is not None):  # before any process starts
            check_writable_folder(cache.entry_dir, flag, given=folder)
        started = time.perf_counter()
        if launched is not None:
            _build_as_launched_rank(cache, views, keys, launched, config.sam_device)
            if launched[0] != 0:  # rank 0 reports and draws the previews
                return {"entry_dir": cache.entry_dir, "keys": keys, "previews": [], "dataset": dataset_dir(config.data)}
            keys = cache.build_all(views, keys=keys, progress=False)  # every entry is there: checks them
        elif devices:
            keys = build_on_ranks(cache, views, devices, write_check=(folder, flag))
        else:
            keys = cache.build_all(views, keys=keys)
        elapsed = time.perf_counter() - started
    print(f"vote maps of {len(views)} views ({source.name} masks, levels {list(source.levels)}) in {cache.entry_dir}")
    if missing:
        processes = len(devices) or (launched[1] if launched is not None else 1)
        print(
            f"made {missing} in {elapsed:.1f} s ({missing / max(elapsed, 1e-9):.2f} images/s, "
            f"{processes} process{'es' if processes > 1 else ''})"
        )
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
