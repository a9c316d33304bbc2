"""The training views and their masks, per vote level, for the mask check of the instances
(:mod:`votesplat_ns.core.mask_consensus`), read from a loaded run's vote datamanager."""

from __future__ import annotations

from typing import Dict, List, Sequence, Tuple

import numpy as np

from votesplat_ns.core.cameras import PinholeView, scaled_view
from votesplat_ns.core.mask_consensus import (
    DEFAULT_DEPTH_TOLERANCE,
    drawn_masks,
    regroup_with_masks,
    seen_mask_table,
    seen_pixels,
)
from votesplat_ns.core.scene import TrainedScene
from votesplat_ns.core.vote_maps import VoteMaps
from votesplat_ns.ns.run import camera_view, evenly_spaced

# Every training view up to 64: on the tuning scenes (48 training views) all of them gave the
# check more evidence on small objects than 32 (instance mIoU 0.902 -> 0.906 GT, 0.904 -> 0.908
# noisy; BENCHMARKS.md "Training-mask check"); the cost grows with the views on a CPU.
DEFAULT_MASK_VIEWS = 64
DEFAULT_MASK_VIEW_WIDTH = 320


def training_vote_views(
    datamanager, max_views: int = DEFAULT_MASK_VIEWS, max_width: int = DEFAULT_MASK_VIEW_WIDTH
) -> Tuple[List[PinholeView], List[VoteMaps]]:
    """Up to ``max_views`` evenly spaced training views of the vote ``datamanager``, at most
    ``max_width`` wide, and their vote maps (every level) at that size."""
    cameras = datamanager.train_dataset.cameras
    indices = evenly_spaced(len(cameras), max_views)
    views = [scaled_view(camera_view(cameras, i), max_width=max_width) for i in indices]
    maps = [datamanager.vote_maps_for_train_view(i, v.height, v.width) for i, v in zip(indices, views)]
    return views, maps


def training_mask_views(
    pipeline, level_names: Sequence[str], max_views: int = DEFAULT_MASK_VIEWS, max_width: int = DEFAULT_MASK_VIEW_WIDTH
) -> Tuple[List[PinholeView], Dict[str, List[np.ndarray]]]:
    """The views of :func:`training_vote_views` and, for each level in ``level_names`` (names of the
    datamanager's vote levels), their mask labels [H, W]."""
    datamanager = pipeline.datamanager
    if not hasattr(datamanager, "vote_levels"):
        raise ValueError("the run's datamanager has no training masks (not the votesplat vote datamanager)")
    known = list(datamanager.vote_levels)
    missing = [name for name in level_names if name not in known]
    if missing:
        raise ValueError(f"the run's masks have levels {known}; no masks for {missing}")
    views, maps = training_vote_views(datamanager, max_views, max_width)
    masks = {name: [np.asarray(m.labels)[known.index(name)].astype(np.int64) for m in maps] for name in level_names}
    return views, masks


def mask_check(
    pipeline,
    scene: TrainedScene,
    rasterize_fn,
    max_views: int = DEFAULT_MASK_VIEWS,
    max_width: int = DEFAULT_MASK_VIEW_WIDTH,
    evidence: str = "centre",
    depth_tolerance: float = DEFAULT_DEPTH_TOLERANCE,
    **options,
):
    """The ``refine`` callback of :func:`votesplat_ns.core.clustering.cluster_levels` that checks the
    instances of a loaded run (``pipeline`` and its ``scene``) against its training masks
    (``options``: those of :func:`votesplat_ns.core.mask_consensus.regroup_with_masks`).

    ``evidence`` says where a Gaussian lies in a view: ``centre`` (default), the mask under its
    projected centre when that is not deeper than ``depth_tolerance`` behind the rendered depth
    (:func:`~votesplat_ns.core.mask_consensus.seen_pixels`, one render per view, shared by the
    levels); ``blend``, the mask holding most of its blending weight
    (:func:`~votesplat_ns.core.mask_consensus.drawn_masks`, one render and backward per view, level
    and 32 masks). On the tuning scenes the two were within 0.005 instance mIoU and ``centre`` kept
    more part mIoU at half the cost (BENCHMARKS.md "Training-mask check").
    """
    if evidence not in ("centre", "blend"):
        raise ValueError(f"evidence must be 'centre' or 'blend' (got {evidence!r})")
    views, masks = training_mask_views(pipeline, scene.level_names, max_views, max_width)
    finite = scene.finite()
    means, quats, scales, opacities = scene.gaussians(finite)[:4]
    tables: Dict[str, np.ndarray] = {}
    if evidence == "blend":
        for name in scene.level_names:
            tables[name] = np.full((len(views), finite.shape[0]), -1, dtype=np.int32)
            for v, view in enumerate(views):
                drawn = drawn_masks(rasterize_fn, means, quats, scales, opacities, view, masks[name][v])
                tables[name][v, finite] = drawn
    else:
        pixels = []
        for view in views:
            seen = np.full(finite.shape[0], -1, dtype=np.int64)  # non-finite Gaussians are never seen
            seen[finite] = seen_pixels(rasterize_fn, means, quats, scales, opacities, view, depth_tolerance)
            pixels.append(seen)
        tables = {name: seen_mask_table(pixels, masks[name]) for name in scene.level_names}

    def refine(index: int, name: str, ids: np.ndarray):
        votes = np.where(
            (scene.vote_support[:, index] > 0)[:, None], scene.means + scene.vote_offsets[:, index], np.nan
        )
        return regroup_with_masks(ids, scene.means, tables[name], votes=votes, **options)

    return refine
