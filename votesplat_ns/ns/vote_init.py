"""The lifted start of a retrofit's vote offsets (:mod:`votesplat_ns.core.vote_init`), read from the
vote datamanager's training views and vote maps."""

from __future__ import annotations

import time

import torch

from votesplat_ns.core.vote_init import LiftedVotes, lifted_votes
from votesplat_ns.ns.mask_views import DEFAULT_MASK_VIEW_WIDTH, DEFAULT_MASK_VIEWS, training_vote_views
from votesplat_ns.ns.rasterizer import rasterize


def lifted_offsets(
    model, datamanager, max_views: int = DEFAULT_MASK_VIEWS, max_width: int = DEFAULT_MASK_VIEW_WIDTH
) -> LiftedVotes:
    """Lifted offsets [N, L, 3] of ``model``'s Gaussians from up to ``max_views`` evenly spaced training
    views at most ``max_width`` wide (the views and size of the mask check: one render per view)."""
    views, maps = training_vote_views(datamanager, max_views, max_width)
    return lifted_votes(rasterize, model.means, model.quats, model.scales.exp(), model.opacities.sigmoid(), views, maps)


def start_offsets_lifted(model, datamanager, log=print) -> float:
    """Write the lifted offsets into ``model``'s ``vote_offsets``; returns the seconds it took.

    ``vote_support`` counts the views that gave a Gaussian its lifted vote, so a Gaussian seen in a
    mask counts as supervised (foreground, subject to the end-of-training mask share) even if no
    later step samples one of its pixels: it carries a vote target, not the zero offset of the
    background.
    """
    start = time.perf_counter()
    with_grad = model.gauss_params["vote_offsets"]
    with torch.no_grad():
        result = lifted_offsets(model, datamanager)
        with_grad.copy_(result.offsets.to(with_grad.device, with_grad.dtype))
        support = model.gauss_params["vote_support"]
        support.add_(result.views.to(support.device, support.dtype))
    seconds = time.perf_counter() - start
    share = (result.views > 0).float().mean(dim=0).tolist()
    log(
        f"Retrofit: lifted vote offsets of {with_grad.shape[0]} Gaussians in {seconds:.1f} s "
        f"(seen in a mask: {', '.join(f'{s:.1%}' for s in share)} per level)"
    )
    return seconds
