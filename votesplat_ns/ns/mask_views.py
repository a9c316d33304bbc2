"""The training views and their masks, per vote level, for the mask check of the instances
(:mod:`votesplat_ns.core.mask_consensus`), read from a loaded run's vote datamanager."""

from __future__ import annotations

from typing import Dict, Sequence

import numpy as np
import torch

from votesplat_ns.core.cameras import scaled_view
from votesplat_ns.core.mask_consensus import MaskView, regroup_with_masks, seen_mask_table, seen_pixels
from votesplat_ns.ns.run import camera_view

DEFAULT_MASK_VIEWS = 32
DEFAULT_MASK_VIEW_WIDTH = 320


def training_mask_views(
    pipeline, level_names: Sequence[str], max_views: int = DEFAULT_MASK_VIEWS, max_width: int = DEFAULT_MASK_VIEW_WIDTH
) -> Dict[str, list]:
    """Up to ``max_views`` evenly spaced training views, at most ``max_width`` wide, with the
    masks of each level in ``level_names`` (names of the datamanager's vote levels)."""
    datamanager = pipeline.datamanager
    if not hasattr(datamanager, "vote_levels"):
        raise ValueError("the run's datamanager has no training masks (not the votesplat vote datamanager)")
    known = list(datamanager.vote_levels)
    missing = [name for name in level_names if name not in known]
    if missing:
        raise ValueError(f"the run's masks have levels {known}; no masks for {missing}")
    cameras = datamanager.train_dataset.cameras
    count = len(cameras)
    picks = sorted({int(round(x)) for x in np.linspace(0, count - 1, min(max_views, count))}) if max_views > 0 else []
    views: Dict[str, list] = {name: [] for name in level_names}
    for index in picks:
        view = scaled_view(camera_view(cameras, index), max_width=max_width)
        labels = np.asarray(datamanager.vote_maps_for_train_view(index, view.height, view.width).labels)
        for name in level_names:
            views[name].append(MaskView(view.viewmat, view.K, labels[known.index(name)].astype(np.int64)))
    return views


def mask_check(
    pipeline, rasterize_fn, max_views: int = DEFAULT_MASK_VIEWS, max_width: int = DEFAULT_MASK_VIEW_WIDTH, **options
):
    """The ``refine`` callback of :func:`votesplat_ns.core.clustering.cluster_levels` that checks a
    loaded run's instances against its training masks (``options``: those of
    :func:`votesplat_ns.core.mask_consensus.regroup_with_masks`). The depth test of every view is
    made once and shared by the levels."""
    model = pipeline.model
    params = model.gauss_params
    means = params["means"].detach().float()
    quats = params["quats"].detach().float()
    scales = torch.exp(params["scales"].detach().float())
    opacities = torch.sigmoid(params["opacities"].detach().float()).reshape(-1)
    level_names = tuple(str(name) for name in model.config.vote_levels)
    views = training_mask_views(pipeline, level_names, max_views, max_width)
    pixels = [seen_pixels(rasterize_fn, means, quats, scales, opacities, view) for view in views[level_names[0]]]
    points = means.cpu().numpy()

    def refine(index: int, name: str, ids: np.ndarray):
        table = seen_mask_table(pixels, views[name])
        return regroup_with_masks(ids, points, table, **options)

    return refine
