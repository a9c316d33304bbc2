"""The training views and their masks, per vote level, for the mask check of the instances
(:mod:`votesplat_ns.core.mask_consensus`), read from a loaded run's vote datamanager."""

from __future__ import annotations

from typing import Dict, List, Sequence, Tuple

import numpy as np

from votesplat_ns.core.cameras import PinholeView, scaled_view
from votesplat_ns.core.mask_consensus import regroup_with_masks, seen_mask_table, seen_pixels
from votesplat_ns.core.scene import TrainedScene
from votesplat_ns.ns.run import camera_view, evenly_spaced

DEFAULT_MASK_VIEWS = 32
DEFAULT_MASK_VIEW_WIDTH = 320


def training_mask_views(
    pipeline, level_names: Sequence[str], max_views: int = DEFAULT_MASK_VIEWS, max_width: int = DEFAULT_MASK_VIEW_WIDTH
) -> Tuple[List[PinholeView], Dict[str, List[np.ndarray]]]:
    """Up to ``max_views`` evenly spaced training views, at most ``max_width`` wide, and for each
    level in ``level_names`` (names of the datamanager's vote levels) their mask labels [H, W]."""
    datamanager = pipeline.datamanager
    if not hasattr(datamanager, "vote_levels"):
        raise ValueError("the run's datamanager has no training masks (not the votesplat vote datamanager)")
    known = list(datamanager.vote_levels)
    missing = [name for name in level_names if name not in known]
    if missing:
        raise ValueError(f"the run's masks have levels {known}; no masks for {missing}")
    cameras = datamanager.train_dataset.cameras
    views: List[PinholeView] = []
    masks: Dict[str, List[np.ndarray]] = {name: [] for name in level_names}
    for index in evenly_spaced(len(cameras), max_views):
        view = scaled_view(camera_view(cameras, index), max_width=max_width)
        labels = np.asarray(datamanager.vote_maps_for_train_view(index, view.height, view.width).labels)
        views.append(view)
        for name in level_names:
            masks[name].append(labels[known.index(name)].astype(np.int64))
    return views, masks


def mask_check(
    pipeline,
    scene: TrainedScene,
    rasterize_fn,
    max_views: int = DEFAULT_MASK_VIEWS,
    max_width: int = DEFAULT_MASK_VIEW_WIDTH,
    **options,
):
    """The ``refine`` callback of :func:`votesplat_ns.core.clustering.cluster_levels` that checks the
    instances of a loaded run (``pipeline`` and its ``scene``) against its training masks
    (``options``: those of :func:`votesplat_ns.core.mask_consensus.regroup_with_masks`). The depth
    test of every view is made once and shared by the levels."""
    views, masks = training_mask_views(pipeline, scene.level_names, max_views, max_width)
    finite = scene.finite()
    means, quats, scales, opacities, _, _ = scene.gaussians(finite)
    pixels = []
    for view in views:
        seen = np.full(finite.shape[0], -1, dtype=np.int64)  # non-finite Gaussians are never seen
        seen[finite] = seen_pixels(rasterize_fn, means, quats, scales, opacities, view)
        pixels.append(seen)

    def refine(index: int, name: str, ids: np.ndarray):
        return regroup_with_masks(ids, scene.means, seen_mask_table(pixels, masks[name]), **options)

    return refine
