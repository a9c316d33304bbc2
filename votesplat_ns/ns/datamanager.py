"""Full-image datamanager that adds each training view's 2D vote maps to the batch.

``next_train`` returns splatfacto's ``(camera, data)`` plus
  - ``data["vote_labels"]``: int16 [L, H, W] mask ids (0 = no mask; int32 for a view with more than 32767
    masks in a level: ``core.vote_maps.label_tensor``),
  - ``data["vote_centroids"]``: float32 [L, Kmax+1, 2] (column, row) per id in pixel-index
    coordinates, NaN-padded (row 0 is always NaN),
  - ``data["vote_pixels"]``: int32 [C] flat indices of the pixels that carry a vote
    (``core.vote_maps.voting_pixels``), among which training samples its vote pixels,
all at exactly the resolution of ``data["image"]``, in host memory (``cache_vote_maps`` "cpu", pinned on CUDA)
or on the training device ("gpu"). The level names are published as
``train_dataset.metadata["vote_levels"]`` (the pipeline passes that metadata to the model).

Masks are made once per view by a :mod:`mask source <votesplat_ns.core.mask_sources>` at the image
file's resolution and cached on disk by :class:`~votesplat_ns.core.vote_cache.VoteCache`; the
datamanager only maps them to the training frame:
  - images downscaled (dataparser ``images_N/``, ``camera_res_scale_factor``): labels
    nearest-neighbour, centroids rescaled in the continuous frame (``resize_vote_maps``);
  - images undistorted by nerfstudio (cameras with distortion): the label images are warped
    with the same maps nerfstudio uses for the image (nearest-neighbour) and cropped alike, and
    the centroids are recomputed from the warped masks, since undistortion is not a similarity
    and does not carry a mask's mean to the warped mask's mean.

Cache location (``cache_dir``): by default ``outputs/<dataset folder name>/votesplat_cache``
relative to the working directory, i.e. beside ns-train's default run folders
(``outputs/<experiment>/votesplat/<timestamp>``), shared by all runs on that dataset, never
inside the dataset. With ``ns-train --output-dir D`` pass ``--pipeline.datamanager.cache-dir``
as well to keep the cache beside the runs.

The checks of the run's inputs are in :mod:`votesplat_ns.ns.data_checks`, the SAM options in
:mod:`votesplat_ns.ns.mask_settings`.
"""

from __future__ import annotations

import functools
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from copy import deepcopy
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple, Type

import cv2
import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.utils.rich_utils import CONSOLE

from votesplat_ns.core.mask_sources import (
    SAM_CHECKPOINT_FILES,
    SAM_LEVELS,
    DatasetMaskSource,
    FolderMaskSource,
    MaskSource,
    make_mask_source,
    read_image_rgb,
)
from votesplat_ns.core.vote_cache import VoteCache, VoteOptions
from votesplat_ns.core.vote_cache_ranks import rank_share
from votesplat_ns.core.vote_maps import (
    DEFAULT_BORDER_MASKS,
    VoteMaps,
    label_tensor,
    resize_label_images,
    resize_vote_maps,
    vote_maps_from_labels,
    voting_pixels,
)
from votesplat_ns.errors import VoteSplatInputError, check_device_available, writing_into
from votesplat_ns.ns.data_checks import (
    CACHE_DIR_FLAG,
    DATASET_LEVELS,
    check_cache_outside_dataset,
    check_data_input,
    check_vote_schedule,
    default_cache_dir,
)
from votesplat_ns.ns.data_parallel import distributed_ranks, training_ranks
from votesplat_ns.ns.mask_settings import SamOptions
from votesplat_ns.ns.retrofit import retrofit_reference

# Threads that prepare the training views' vote batches in the background (training's own thread keeps
# running; two keep the GIL mostly free for it).
PREFETCH_THREADS = 2


@dataclass
class VoteDataManagerConfig(SamOptions, FullImageDatamanagerConfig):
    """FullImageDatamanager plus per-view 2D vote maps (VoteSplat Sec. 3.2); the SAM options are :class:`SamOptions`."""

    _target: Type = field(default_factory=lambda: VoteDataManager)
    mask_source: Literal["auto", "dataset", "folder", "sam"] = "auto"
    """Where masks come from: dataset (<level>_mask_path in transforms.json), folder, sam; auto: dataset if listed, else sam."""
    mask_levels: Optional[Tuple[str, ...]] = None
    """Mask levels in order, one vote map each (default: instance part / the mask folder's sub-folders / SAM's 4 levels)."""
    mask_folder: Optional[Path] = None
    """For mask-source folder: a folder holding <level>/<image file stem>.png label images (0 = no mask)."""
    border_masks: Literal["vote", "mask_only", "drop"] = DEFAULT_BORDER_MASKS
    """A mask touching the image border: vote (its visible part's centroid), mask_only (no vote target) or drop."""
    cache_dir: Optional[Path] = None
    """Where masks and 2D votes are cached (default: outputs/<dataset folder name>/votesplat_cache)."""
    vote_maps_in_memory: int = 128
    """Training views whose vote maps stay in memory (up to 4 MB a 960x540 view with 2 levels; README.md, Masks)."""
    cache_vote_maps: Literal["cpu", "gpu"] = "cpu"
    """Where the vote maps are kept: cpu (pinned RAM, copied to the GPU each vote step) or gpu (on the device, as cache_images)."""

    @property
    def dataset_path(self) -> Path:
        return Path(self.data if self.data is not None else self.dataparser.data)

    def resolved_mask_source(self) -> str:
        """The mask source 'auto' stands for on this dataset."""
        if self.mask_source != "auto":
            return self.mask_source
        return "dataset" if DatasetMaskSource.has_masks(self.dataset_path) else "sam"

    def resolved_levels(self) -> Tuple[str, ...]:
        """The mask levels, known without building the source (no SAM checkpoint needed)."""
        if self.mask_levels:
            return tuple(self.mask_levels)
        kind = self.resolved_mask_source()
        if kind == "dataset":
            return DATASET_LEVELS
        if kind == "sam":
            return SAM_LEVELS
        return FolderMaskSource(self._require_mask_folder()).levels

    def _require_mask_folder(self) -> Path:
        if self.mask_folder is None:
            raise VoteSplatInputError(
                "mask source 'folder' needs --pipeline.datamanager.mask-folder <root> (<root>/<level>/<image_stem>.png)"
            )
        return Path(self.mask_folder)

    def make_mask_source(self) -> MaskSource:
        kind = self.resolved_mask_source()
        if kind == "sam" and self.sam_checkpoint is None:
            reason = (
                "this dataset lists no instance_mask_path, so masks come from SAM; "
                if self.mask_source == "auto"
                else ""
            )
            raise VoteSplatInputError(
                f"{reason}give the SAM checkpoint with --pipeline.datamanager.sam-checkpoint /path/to/"
                f"{SAM_CHECKPOINT_FILES[self.sam_model_type]} (the official checkpoints are listed in the README of "
                "facebookresearch/segment-anything; nothing is downloaded), or use --pipeline.datamanager.mask-source folder"
            )
        if kind == "folder":
            self._require_mask_folder()
        return make_mask_source(
            kind,
            data=self.dataset_path,
            levels=self.mask_levels,
            mask_folder=self.mask_folder,
            sam_checkpoint=self.sam_checkpoint,
            sam_model_type=self.sam_model_type,
            sam_device=self.sam_device,
            sam_options=self.sam_generator_options(),
        )


class VoteDataManager(FullImageDatamanager[InputDataset]):
    config: VoteDataManagerConfig

    def __init__(
        self, config: VoteDataManagerConfig, device="cpu", test_mode="val", world_size=1, local_rank=0, **kwargs
    ):
        # bad input fails here with one actionable line (votesplat_ns/errors.py), before images are loaded or masks made
        check_device_available(device)
        where = None if test_mode == "val" else f"dataset {config.dataset_path} (the data path of the run's config.yml)"
        check_data_input(config, check_images=test_mode != "inference", where=where)
        try:
            super().__init__(
                config, device=device, test_mode=test_mode, world_size=world_size, local_rank=local_rank, **kwargs
            )
        except FileNotFoundError as err:
            if err.filename is None:
                raise
            raise VoteSplatInputError(
                f"{where or f'--data {config.dataset_path}'}: {err.filename} not found; check that the dataset folder is complete"
            ) from err
        # nerfstudio overwrites the train cameras when it undistorts images; the label images
        # must be warped from the cameras as loaded.
        self._cameras_as_loaded: Cameras = deepcopy(self.train_dataset.cameras)
        self._vote_cache: Optional[VoteCache] = None
        self._vote_keys: Optional[List[str]] = None
        # per train view: the batch tensors at the last requested resolution (an LRU of vote_maps_in_memory views)
        self._in_memory: "OrderedDict[int, Dict[str, torch.Tensor]]" = OrderedDict()
        # per train view not yet in _in_memory: its batch being prepared in the background (from the first step)
        self._prefetch: Optional[Dict[int, "Future[Dict[str, torch.Tensor]]"]] = None
        # the pipeline hands train_dataset.metadata to the model, which sizes its offsets by it
        self.train_dataset.metadata["vote_levels"] = self.config.resolved_levels()
        # whether this datamanager feeds ns-train (the model then prepares its vote kernels as it is built)
        self.train_dataset.metadata["vote_training"] = test_mode == "val"
        # a retrofit from a PLY (model.retrofit_from) finds the file's frame with these frames and views
        self.train_dataset.metadata["retrofit_reference"] = functools.partial(retrofit_reference, self)
        if test_mode == "val":  # ns-train: make all masks now, before training starts
            self._prepare_votes()

    # ------------------------------------------------------------------ views of this rank
    @property
    def view_shard(self) -> Tuple[int, int]:
        """(rank, ranks): this process trains on the views rank, rank + ranks, ... (several processes: a
        data-parallel retrofit, ``ns/data_parallel.py``); (0, 1) alone."""
        return training_ranks(self.world_size, self.local_rank)

    def sample_train_cameras(self):
        """nerfstudio's order of the training views, keeping this rank's share (every rank draws the same order)."""
        order = super().sample_train_cameras()
        rank, ranks = self.view_shard
        if ranks == 1:
            return order
        own = [index for index in order if index % ranks == rank]
        if not own:
            raise VoteSplatInputError(
                f"{ranks} processes share {len(self.train_dataset)} training views, so rank {rank} has none: "
                f"train on {len(self.train_dataset)} or fewer (--machine.num-devices)"
            )
        return own

    # ------------------------------------------------------------------ vote cache
    @property
    def vote_levels(self) -> Tuple[str, ...]:
        """Names of the vote levels, in the order of ``data["vote_labels"]``."""
        return tuple(self.train_dataset.metadata["vote_levels"])

    @property
    def vote_cache_dir(self) -> Path:
        data = self.config.dataset_path
        cache_dir = Path(self.config.cache_dir) if self.config.cache_dir is not None else default_cache_dir(data)
        check_cache_outside_dataset(cache_dir, data)
        return cache_dir

    def _prepare_votes(self) -> None:
        if self._vote_keys is not None:
            return
        source = self.config.make_mask_source()
        if tuple(source.levels) != self.vote_levels:
            raise ValueError(
                f"mask source levels {list(source.levels)} differ from the announced {list(self.vote_levels)}"
            )
        cache_dir = self.vote_cache_dir
        views = [(index, Path(path)) for index, path in enumerate(self.train_dataset.image_filenames)]
        with writing_into(cache_dir, CACHE_DIR_FLAG):
            cache = VoteCache(cache_dir, source, VoteOptions(border_masks=self.config.border_masks))
            CONSOLE.log(f"Vote maps: {source.name} masks, levels {list(source.levels)}, cache {cache.entry_dir}")
            ranks = distributed_ranks()
            if ranks is not None:  # several processes: each makes its share (on its GPU), then all wait for all
                rank, world = ranks
                cache.build_all(
                    rank_share(views, rank, world),
                    progress=rank == 0,
                    description=f"Making vote maps ({source.name} masks; rank 0's share of {world})",
                )
                torch.distributed.barrier()
            self._vote_keys = cache.build_all(views, description=f"Making vote maps ({source.name} masks)")
        self._vote_cache = cache
        if not any(self._view_has_votes(key) for key in self._vote_keys):
            # training would run to the end without a single vote; only the export would notice
            border = f", or touches the image border (--pipeline.datamanager.border-masks {self.config.border_masks})"
            CONSOLE.print(
                f"Warning: no mask of the {len(views)} training views gives a vote (every mask is empty"
                f"{border if self.config.border_masks != 'vote' else ''}), so this run learns no instances; "
                f"look at the masks with: votesplat masks --data {self.config.dataset_path} --preview 4",
                style="bold yellow",
                soft_wrap=True,
                markup=False,
            )

    def _view_has_votes(self, key: str) -> bool:
        assert self._vote_cache is not None
        stored = self._vote_cache.load(key)
        # a mask votes when its centroid is finite (border_masks=mask_only keeps masks without one)
        return stored is not None and any(bool(np.isfinite(table[1:]).any()) for table in stored.centroids)

    def get_training_callbacks(self, training_callback_attributes) -> List:
        callbacks = super().get_training_callbacks(training_callback_attributes)
        trainer = training_callback_attributes.trainer
        model = getattr(training_callback_attributes.pipeline, "model", None)
        if trainer is not None and model is not None:  # the step range is known only now, after a --load-dir
            check_vote_schedule(model, trainer._start_step, trainer.config.max_num_iterations)
        return callbacks

    def _load_images(self, split: Literal["train", "eval"], cache_images_device: Literal["cpu", "gpu"]):
        try:
            return super()._load_images(split, cache_images_device)
        except Exception:
            # nerfstudio's loader names no file (PIL: "image file is truncated"); find it and name it
            dataset = self.train_dataset if split == "train" else self.eval_dataset
            for path in dataset.image_filenames:
                read_image_rgb(path)
            raise

    def vote_maps_for_train_view(self, index: int, height: int, width: int) -> VoteMaps:
        """The view's vote maps mapped to a training image of ``height`` x ``width`` pixels."""
        self._prepare_votes()
        assert self._vote_cache is not None and self._vote_keys is not None
        image_path = Path(self.train_dataset.image_filenames[index])
        stored = self._vote_cache.load(self._vote_keys[index])
        if stored is None:  # entry removed or damaged since start-up
            with writing_into(self._vote_cache.entry_dir, CACHE_DIR_FLAG):
                stored = self._vote_cache.get(index, image_path)
        return self._to_training_frame(stored, index, height, width, image_path)

    def _to_training_frame(self, stored: VoteMaps, index: int, height: int, width: int, image_path: Path) -> VoteMaps:
        camera = self._cameras_as_loaded[index].reshape(())
        distortion = camera.distortion_params
        if distortion is None or bool(torch.all(distortion == 0)):
            return resize_vote_maps(stored, height, width)
        loaded_h, loaded_w = int(camera.height.item()), int(camera.width.item())
        labels = resize_label_images(stored.labels, loaded_h, loaded_w)
        warped = [undistort_label_image(np.asarray(level_labels), camera, distortion) for level_labels in labels]
        if warped[0].shape != (height, width):
            raise ValueError(
                f"undistorted vote labels of {image_path} are {warped[0].shape[1]}x{warped[0].shape[0]} "
                f"but nerfstudio's undistorted image is {width}x{height}"
            )
        return vote_maps_from_labels(warped, self.config.border_masks, stored.level_names)

    # ------------------------------------------------------------------ batches
    def next_train(self, step: int) -> Tuple[Cameras, Dict]:
        camera, data = super().next_train(step)
        assert camera.metadata is not None
        index = int(camera.metadata["cam_idx"])
        # The kept tensors: in host memory (cache_vote_maps "cpu") the model copies them to its device only on the
        # steps that vote (vote_every_n_steps), instead of up to ~4 MB host-to-device on every step.
        data.update(self.kept_vote_batch(index, int(data["image"].shape[0]), int(data["image"].shape[1])))
        if self._prefetch is None:
            self._start_prefetch()
        return camera, data

    def _start_prefetch(self) -> None:
        """Prepares the vote batches of the training views in background threads, at their cached images'
        resolution: reading, undistorting and pinning a view costs ms to 0.2 s of CPU, which would
        otherwise stall the step that first visits it (cv2, numpy and torch release the GIL for it)."""
        self._prefetch = {}
        rank, ranks = self.view_shard  # this rank's views only
        views = [i for i in range(len(self.cached_train)) if i not in self._in_memory and i % ranks == rank]
        pool = ThreadPoolExecutor(max_workers=PREFETCH_THREADS, thread_name_prefix="vote-maps")
        for index in views[: max(0, self.config.vote_maps_in_memory - len(self._in_memory))]:
            image = self.cached_train[index]["image"]
            self._prefetch[index] = pool.submit(
                self._vote_batch_tensors, index, int(image.shape[0]), int(image.shape[1])
            )
        pool.shutdown(wait=False)  # the threads end when the queue is done

    def vote_batch(
        self, index: int, height: Optional[int] = None, width: Optional[int] = None
    ) -> Dict[str, torch.Tensor]:
        """``vote_labels`` [L,H,W] and ``vote_centroids`` [L,K+1,2] of train view ``index``, on the device.

        At the training image's resolution unless ``height``/``width`` are given.
        """
        return {name: tensor.to(self.device) for name, tensor in self.kept_vote_batch(index, height, width).items()}

    def kept_vote_batch(
        self, index: int, height: Optional[int] = None, width: Optional[int] = None
    ) -> Dict[str, torch.Tensor]:
        """``vote_batch`` as kept: in host memory, or on the device under ``cache_vote_maps`` "gpu" (the kept
        tensors: do not modify them)."""
        if height is None or width is None:
            camera = self.train_dataset.cameras[index]
            height, width = int(camera.height.item()), int(camera.width.item())
        cached = self._in_memory.get(index)
        if cached is None or tuple(cached["vote_labels"].shape[1:]) != (height, width):
            prefetched = self._prefetch.pop(index, None) if self._prefetch else None
            cached = prefetched.result() if prefetched is not None else None  # re-raises the worker's error
            if cached is None or tuple(cached["vote_labels"].shape[1:]) != (height, width):
                cached = self._vote_batch_tensors(index, height, width)
            self._in_memory[index] = cached
            while len(self._in_memory) > max(0, self.config.vote_maps_in_memory):
                self._in_memory.popitem(last=False)
        else:
            self._in_memory.move_to_end(index)
        return dict(cached)

    def _vote_batch_tensors(self, index: int, height: int, width: int) -> Dict[str, torch.Tensor]:
        """The batch tensors of train view ``index`` at ``height`` x ``width``, where ``cache_vote_maps`` keeps them."""
        vote_maps = self.vote_maps_for_train_view(index, height, width)
        labels = label_tensor(vote_maps.labels)
        centroids = torch.from_numpy(vote_maps.padded_centroids())
        tensors = {"vote_labels": labels, "vote_centroids": centroids, "vote_pixels": voting_pixels(labels, centroids)}
        return place_vote_batch(tensors, torch.device(self.device), self.config.cache_vote_maps)


def place_vote_batch(
    tensors: Dict[str, torch.Tensor], device: torch.device, cache: Literal["cpu", "gpu"]
) -> Dict[str, torch.Tensor]:
    """A view's vote tensors where ``cache_vote_maps`` keeps them: on ``device`` for "gpu"; in host memory for
    "cpu", page-locked when ``device`` is CUDA (the model's non_blocking copy is then asynchronous: a pageable
    copy makes the host wait for the GPU's queue on every vote step)."""
    if cache == "gpu":
        return {name: tensor.to(device) for name, tensor in tensors.items()}
    if device.type == "cuda":
        return {name: tensor.pin_memory() for name, tensor in tensors.items()}
    return tensors


def undistort_label_image(labels: np.ndarray, camera: Cameras, distortion: torch.Tensor) -> np.ndarray:
    """Warp and crop a label image exactly as nerfstudio 1.1.5 undistorts the image, without blending ids.

    Mirrors ``full_images_datamanager._undistort_image`` (same new camera matrix, same crop)
    but samples nearest-neighbour instead of bilinearly.
    """
    max_id = int(labels.max()) if labels.size else 0
    if max_id > np.iinfo(np.uint16).max:
        raise ValueError(f"a view has {max_id} masks; at most 65535 masks per level can be undistorted")
    source = np.ascontiguousarray(labels.astype(np.uint16))
    height, width = source.shape
    K = camera.get_intrinsics_matrices().numpy().astype(np.float64)
    params = distortion.numpy().astype(np.float64)
    camera_type = camera.camera_type.item()
    if camera_type == CameraType.PERSPECTIVE.value:
        if params[3] != 0:
            raise ValueError(
                "nerfstudio cannot undistort with the 4th Brown parameter (k4); only k1, k2, k3, p1, p2 may be non-zero"
            )
        opencv_params = np.array([params[0], params[1], params[4], params[5], params[2], params[3], 0, 0])
        K[0, 2] -= 0.5  # OpenCV's pixel centres are at integers
        K[1, 2] -= 0.5
        if np.any(opencv_params):
            new_K, roi = cv2.getOptimalNewCameraMatrix(K, opencv_params, (width, height), 0)
            # no rectification: the identity, as OpenCV takes an empty R
            map_x, map_y = cv2.initUndistortRectifyMap(
                K, opencv_params, np.eye(3), new_K, (width, height), cv2.CV_32FC1
            )
            warped = cv2.remap(
                source, map_x, map_y, interpolation=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=(0,)
            )
        else:
            warped, roi = source, (0, 0, width, height)
        x, y, w, h = roi
        return warped[y : y + h, x : x + w].astype(np.int32)
    if camera_type == CameraType.FISHEYE.value:
        K[0, 2] -= 0.5
        K[1, 2] -= 0.5
        fisheye_params = params[:4]
        new_K = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(
            K, fisheye_params, (width, height), np.eye(3), balance=0
        )
        map_x, map_y = cv2.fisheye.initUndistortRectifyMap(
            K, fisheye_params, np.eye(3), new_K, (width, height), cv2.CV_32FC1
        )
        warped = cv2.remap(
            source, map_x, map_y, interpolation=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=(0,)
        )
        return warped.astype(np.int32)
    raise ValueError(
        f"vote maps for distorted cameras of type {CameraType(camera_type).name} are not supported; "
        "undistort the images first (e.g. COLMAP image_undistorter) so the cameras are pinhole"
    )
