"""The training views and their masks, per vote level, for the mask check of the instances
(:mod:`votesplat_ns.core.mask_consensus`), read from a loaded run's vote datamanager."""

from __future__ import annotations

from typing import Dict, List, Sequence, Tuple

import numpy as np

from votesplat_ns.core.cameras import PinholeView, scaled_view
from votesplat_ns.core.mask_consensus import (
    DEFAULT_DEPTH_TOLERANCE,
    drawn_masks,
    fill_seen_masks,
    regroup_with_masks,
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
    indices, views = _mask_views(datamanager, max_views, max_width)
    maps = [datamanager.vote_maps_for_train_view(i, v.height, v.width) for i, v in zip(indices, views)]
    return views, maps


def _known_levels(pipeline, level_names: Sequence[str]) -> List[str]:
    """The datamanager's vote levels; a level of ``level_names`` it lacks is an error."""
    datamanager = pipeline.datamanager
    if not hasattr(datamanager, "vote_levels"):
        raise ValueError("the run's datamanager has no training masks (not the votesplat vote datamanager)")
    known = list(datamanager.vote_levels)
    missing = [name for name in level_names if name not in known]
    if missing:
        raise ValueError(f"the run's masks have levels {known}; no masks for {missing}")
    return known


def _view_masks(datamanager, known: Sequence[str], level_names: Sequence[str], index: int, view: PinholeView):
    """Train view ``index``'s mask labels [H, W] per level of ``level_names``, at ``view``'s size."""
    labels = np.asarray(datamanager.vote_maps_for_train_view(index, view.height, view.width).labels)
    return {name: labels[known.index(name)].astype(np.int64) for name in level_names}


def training_mask_views(
    pipeline, level_names: Sequence[str], max_views: int = DEFAULT_MASK_VIEWS, max_width: int = DEFAULT_MASK_VIEW_WIDTH
) -> Tuple[List[PinholeView], Dict[str, List[np.ndarray]]]:
    """The views of :func:`training_vote_views` and, for each level in ``level_names`` (names of the
    datamanager's vote levels), their mask labels [H, W]."""
    known = _known_levels(pipeline, level_names)
    indices, views = _mask_views(pipeline.datamanager, max_views, max_width)
    per_view = [_view_masks(pipeline.datamanager, known, level_names, i, view) for i, view in zip(indices, views)]
    return views, {name: [masks[name] for masks in per_view] for name in level_names}


def _mask_views(datamanager, max_views: int, max_width: int) -> Tuple[List[int], List[PinholeView]]:
    cameras = datamanager.train_dataset.cameras
    indices = evenly_spaced(len(cameras), max_views)
    return indices, [scaled_view(camera_view(cameras, i), max_width=max_width) for i in indices]


def mask_tables(
    pipeline,
    scene: TrainedScene,
    rasterize_fn,
    max_views: int = DEFAULT_MASK_VIEWS,
    max_width: int = DEFAULT_MASK_VIEW_WIDTH,
    evidence: str = "centre",
    depth_tolerance: float = DEFAULT_DEPTH_TOLERANCE,
) -> Dict[str, np.ndarray]:
    """Per level of ``scene``, the mask check's table [V, N] of the views of :func:`training_mask_views`: the mask
    each Gaussian lies in per view (0: none, -1: not decided), by ``evidence`` (:func:`mask_check`).

    Built view by view: one view's masks and renders at a time. The tables are its only memory that grows
    with the scene: ``levels x views x N`` int16 (int32 when a view has more than 32767 masks), e.g. 5.1 GB for
    20M Gaussians, 2 levels and 64 views.
    """
    if evidence not in ("centre", "blend"):
        raise ValueError(f"evidence must be 'centre' or 'blend' (got {evidence!r})")
    names = list(scene.level_names)
    known = _known_levels(pipeline, names)
    indices, views = _mask_views(pipeline.datamanager, max_views, max_width)
    finite = scene.finite()
    columns = np.flatnonzero(finite)  # non-finite Gaussians are never seen
    means, quats, scales, opacities = scene.gaussians(finite)[:4]
    # int16 until a view has more masks than it holds (then int32); typed as the wider array it may become
    tables: Dict[str, np.ndarray] = {name: np.full((len(views), finite.shape[0]), -1, dtype=np.int16) for name in names}
    for v, (index, view) in enumerate(zip(indices, views)):
        masks = _view_masks(pipeline.datamanager, known, names, index, view)
        for name in names:
            if masks[name].size and int(masks[name].max()) > np.iinfo(tables[name].dtype).max:
                tables[name] = tables[name].astype(np.int32)
        if evidence == "blend":
            for name in names:
                tables[name][v, columns] = drawn_masks(rasterize_fn, means, quats, scales, opacities, view, masks[name])
        else:
            pixels = seen_pixels(rasterize_fn, means, quats, scales, opacities, view, depth_tolerance)
            for name in names:
                fill_seen_masks(tables[name][v], pixels, masks[name], columns)
    return tables


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
    more part mIoU at half the cost (BENCHMARKS.md "Training-mask check"). The evidence is gathered
    view by view into :func:`mask_tables`.
    """
    tables = mask_tables(pipeline, scene, rasterize_fn, max_views, max_width, evidence, depth_tolerance)

    def refine(index: int, name: str, ids: np.ndarray):
        votes = np.where(
            (scene.vote_support[:, index] > 0)[:, None], scene.means + scene.vote_offsets[:, index], np.nan
        )
        return regroup_with_masks(ids, scene.means, tables[name], votes=votes, **options)

    return refine
