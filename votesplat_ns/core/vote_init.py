"""A starting point for the vote offsets of a retrofit: the 2D votes of the training views lifted to 3D.

A retrofit (vote-only training on a frozen scene) starts the offsets at zero, so every Gaussian
first votes for its own centre and the vote loss has to walk each one to its instance's centre.
The masks already say where that centre is in every training view, so most of the walk can be
skipped.

Why this start is close (paper §3.3, blend then project): the rendered 3D vote of a pixel is the
uniform mean of the votes V^3d_i = p_i + Δp_i of its voting set, projected afterwards. Put each
V^3d_i on the camera ray through the 2D vote target of the mask that Gaussian is seen in (the mask
centroid c of Eq. 3-4), at the Gaussian's own camera depth z_i: points on one ray through the
camera centre average to a point on that ray, so every pixel whose voting set lies in that mask
renders a 3D vote that projects exactly onto c, i.e. zero vote loss in that view, whatever the
depths. One offset has to serve every view, so each Gaussian takes the mean of its lifted points
over the views where it is seen in a mask. Each lifted point is the instance's 3D centre C moved
along that view's ray by the difference between z_i and C's depth; over views from different
directions those moves point different ways and largely cancel, so the mean approximates the
triangulated centroid C. Gaussians seen in no mask keep offset 0, as untrained ones do.

Seen means :func:`votesplat_ns.core.mask_consensus.seen_pixels`: the centre projects onto a pixel
the render covers and is not hidden behind the rendered depth there. Pure torch/numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch

from votesplat_ns.core.cameras import PinholeView
from votesplat_ns.core.mask_consensus import DEFAULT_DEPTH_TOLERANCE, seen_pixels
from votesplat_ns.core.vote_maps import VoteMaps, to_continuous


@dataclass
class LiftedVotes:
    """offsets [N, L, 3] (lifted vote minus mean; 0 where never seen in a mask) and views [N, L]
    (int: the views that gave each Gaussian a lifted point at each level)."""

    offsets: torch.Tensor
    views: torch.Tensor


def point_on_ray(pixel_xy: torch.Tensor, depth: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """World points [M, 3] on the camera rays through ``pixel_xy`` [M, 2] (continuous pixel frame) at
    camera depth ``depth`` [M] (z along the optical axis); the inverse of ``project_to_pixels``."""
    x = (pixel_xy[:, 0] - K[0, 2] - K[0, 1] * (pixel_xy[:, 1] - K[1, 2]) / K[1, 1]) / K[0, 0]
    y = (pixel_xy[:, 1] - K[1, 2]) / K[1, 1]
    camera_points = torch.stack([x * depth, y * depth, depth], dim=-1)
    rotation, translation = viewmat[:3, :3], viewmat[:3, 3]
    return (camera_points - translation) @ rotation  # R^T (p_c - t), row vectors


def lifted_votes(
    rasterize_fn: Callable[..., tuple],
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    views: Sequence[PinholeView],
    vote_maps: Sequence[VoteMaps],
    depth_tolerance: float = DEFAULT_DEPTH_TOLERANCE,
) -> LiftedVotes:
    """Initial vote offsets from the 2D votes of ``views`` (see the module docstring).

    ``vote_maps[v]`` holds view v's labels [L, H, W] at the view's size and its centroid tables
    (pixel-index coordinates; NaN: no vote target). means [N, 3], quats [N, 4], scales [N, 3]
    (linear), opacities [N] in [0, 1]; ``rasterize_fn`` has gsplat's ``rasterization`` signature.
    Gaussians with a non-finite mean, scale or opacity are never seen.
    """
    if len(views) != len(vote_maps):
        raise ValueError(f"{len(views)} views but {len(vote_maps)} vote maps")
    n = means.shape[0]
    num_levels = vote_maps[0].num_levels if vote_maps else 0
    device, dtype = means.device, means.dtype
    total = torch.zeros(n, num_levels, 3, device=device, dtype=torch.float64)
    count = torch.zeros(n, num_levels, device=device, dtype=torch.int64)
    finite = (
        torch.isfinite(means).all(-1)
        & torch.isfinite(scales).all(-1)
        & torch.isfinite(opacities.reshape(n))
        & torch.isfinite(quats).all(-1)
    )
    finite_index = torch.nonzero(finite).squeeze(-1)
    sub_means, sub_quats, sub_scales, sub_opacities = (
        t[finite_index] for t in (means, quats, scales, opacities.reshape(n))
    )
    for view, maps in zip(views, vote_maps):
        if maps.num_levels != num_levels:
            raise ValueError(
                f"vote maps of {view.name or 'a view'} have {maps.num_levels} levels, expected {num_levels}"
            )
        if (maps.height, maps.width) != (view.height, view.width):
            raise ValueError(
                f"vote maps of {view.name or 'a view'} are {maps.width}x{maps.height}, the view {view.width}x{view.height}"
            )
        pixels = torch.as_tensor(
            seen_pixels(rasterize_fn, sub_means, sub_quats, sub_scales, sub_opacities, view, depth_tolerance),
            device=device,
        )
        seen = pixels >= 0
        if not bool(seen.any()):
            continue
        index, pixel = finite_index[seen], pixels[seen]
        viewmat = view.viewmat.to(device=device, dtype=torch.float64)
        K = view.K.to(device=device, dtype=torch.float64)
        points = means[index].to(torch.float64)
        depth = points @ viewmat[2, :3] + viewmat[2, 3]
        flat_labels = torch.as_tensor(np.asarray(maps.labels).astype(np.int64), device=device).reshape(num_levels, -1)
        for level in range(num_levels):
            table = torch.as_tensor(to_continuous(maps.centroids[level]), device=device, dtype=torch.float64)
            target = table[flat_labels[level, pixel]]  # [M, 2]; NaN outside masks and for masks without a vote
            voted = torch.isfinite(target[:, 0])
            if not bool(voted.any()):
                continue
            lifted = point_on_ray(target[voted], depth[voted], viewmat, K)
            total[index[voted], level] += lifted
            count[index[voted], level] += 1
    has = count > 0
    lifted_mean = total / count.clamp_min(1)[..., None]
    offsets = torch.where(has[..., None], lifted_mean - means.to(torch.float64)[:, None, :], torch.zeros_like(total))
    return LiftedVotes(offsets=offsets.to(dtype), views=count)
