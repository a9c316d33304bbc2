"""Which Gaussians are foreground at each mask level: where their rendered weight falls.

A Gaussian counts as foreground at a level when most of its alpha-compositing weight
``w_i(p) = alpha_i(p) T_i(p)`` over the training views lands on pixels that a mask covers at
that level. Vote support alone (a vote gradient was ever received) is not enough: splatfacto
densifies by cloning and splitting, so a large early Gaussian that overlapped an object passes
its support and its offset to children that end up on the table or the wall, never again inside
a mask. Their weights show it.

The weights come from one rasteriser call per view with 2 colour channels per level, all ones:
the gradient of ``sum_p inside_l(p) C_{2l}(p) + outside_l(p) C_{2l+1}(p)`` with respect to
Gaussian i's colour is exactly its weight summed over the pixels inside (outside) the masks.
No nerfstudio import: ``rasterize_fn`` has gsplat 1.4's ``rasterization`` signature (gsplat on
CUDA, ``votesplat_ns.core.rasterize_torch`` on CPU).
"""

from __future__ import annotations

from typing import Any, Callable, Iterable, Tuple

import torch
from torch import Tensor

RasterizeFn = Callable[..., Tuple[Tensor, Tensor, Any]]

DEFAULT_MIN_MASKED_SHARE = 0.5
"""Foreground when more than this share of a Gaussian's weight lies inside masks."""


def mask_exposure(
    rasterize_fn: RasterizeFn,
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    views: Iterable[Tuple[Tensor, Tensor, Tensor]],
    **rasterize_kwargs: Any,
) -> Tensor:
    """Summed rendering weight of each Gaussian inside / outside the masks of each level.

    Args:
        means [N,3], quats [N,4], scales [N,3] (linear), opacities [N] in [0,1].
        views: (viewmat [4,4] world-to-camera OpenCV, K [3,3], labels [L,H,W] int, 0 = no mask).

    Returns [N, L, 2] float: [..., 0] weight on masked pixels, [..., 1] on unmasked pixels.
    """
    n = means.shape[0]
    total = None
    for viewmat, K, labels in views:
        if labels.ndim != 3:
            raise ValueError(f"labels must be [L, H, W], got {list(labels.shape)}")
        levels, height, width = labels.shape
        if total is None:
            total = means.new_zeros(n, levels, 2)
        elif total.shape[1] != levels:
            raise ValueError(f"every view needs the same number of levels ({total.shape[1]}), got {levels}")
        if n == 0:
            continue
        colours = torch.ones(n, 2 * levels, device=means.device, dtype=means.dtype, requires_grad=True)
        with torch.enable_grad():
            render, _, _ = rasterize_fn(
                means.detach(),
                quats.detach(),
                scales.detach(),
                opacities.detach().reshape(-1),
                colours,
                viewmat[None].to(means),
                K[None].to(means),
                int(width),
                int(height),
                **rasterize_kwargs,
            )
            inside = (labels.to(means.device) > 0).to(means.dtype).permute(1, 2, 0)  # [H, W, L]
            selector = torch.stack([inside, 1.0 - inside], dim=-1).reshape(height, width, 2 * levels)
            (weights,) = torch.autograd.grad((render[0] * selector).sum(), colours)
        total += weights.reshape(n, levels, 2)
    if total is None:
        raise ValueError("no views given: the foreground needs at least one training view with its masks")
    return total


def foreground_from_exposure(exposure: Tensor, min_masked_share: float = DEFAULT_MIN_MASKED_SHARE) -> Tensor:
    """[N, L] bool: more than ``min_masked_share`` of the Gaussian's weight lies inside masks.

    A Gaussian with no weight in any view (never visible) is not foreground.
    """
    if not 0.0 <= min_masked_share < 1.0:
        raise ValueError(f"min_masked_share must be in [0, 1), got {min_masked_share}")
    masked, unmasked = exposure[..., 0], exposure[..., 1]
    seen = (masked + unmasked) > 0
    return seen & (masked > min_masked_share * (masked + unmasked))
