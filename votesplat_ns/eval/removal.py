"""Object-removal check: what of an object is still on screen after its instance is deleted.

A user removes an object by deleting the Gaussians of its instance. Whatever Gaussians of the
object the instance missed (fragments, Gaussians hidden behind the surface that never voted) stay
and show as a "ghost". What lies behind the object (the table, the wall) is opaque too and is
uncovered by the removal; it is not a ghost, so a ghost is measured from the GT label of each
Gaussian (the labels of :func:`~votesplat_ns.eval.ground_truth.gaussian_ground_truth`), not from
the opacity of the render:

* after removal, render one channel through the normal rasteriser: 1 for the remaining Gaussians
  whose GT label is the object, 0 for every other remaining Gaussian (which still occludes);
* the blended value at a pixel is the weight sum of alpha_i T_i over the object's leftovers; a GT
  pixel of the object is a ghost pixel when it exceeds ``threshold`` (0.5: the leftovers make up
  most of the pixel);
* ghost fraction = ghost pixels / the object's GT pixels, summed over the views.

``shown_before`` is the same fraction with nothing removed: how much of the object the labelled
Gaussians show at all. It bounds what removal can leave and reads low when the per-Gaussian GT
misses the object (e.g. a thick object whose inner Gaussians lie farther from the surface than
the labelling tolerance: those count as occluders here, not as leftovers).

Cost: one render per view with one channel per object (``shown_before``), then one render per
view per object (each object removes another set of Gaussians), i.e. at most (objects + 1) x
views rasteriser calls; an object with no leftover Gaussian, or a view without its GT pixels, is
skipped (its ghost there is exactly 0). On the bundled demo (4 views of 128 px, 5 objects and 11
parts, the CPU rasteriser on a shared 2-core machine) the check took about 2 minutes of a
4-minute ``votesplat eval``; on the GPU each render takes milliseconds.
"""

from __future__ import annotations

from typing import Callable, Dict, List, Mapping, Optional, Sequence

import numpy as np
import torch

from votesplat_ns.core.cameras import PinholeView, scaled_view

RasterizeFn = Callable[..., tuple]


@torch.no_grad()
def _blended(rasterize_fn: RasterizeFn, gaussians, keep: torch.Tensor, colors: torch.Tensor, view, shape, device):
    means, quats, scales, opacities = gaussians
    height, width = int(shape[0]), int(shape[1])
    view = scaled_view(view, width=width, height=height)
    rendered, _, _ = rasterize_fn(
        means[keep],
        quats[keep],
        scales[keep],
        opacities[keep],
        colors[keep],
        view.viewmat.float().reshape(1, 4, 4).to(device),
        view.K.float().reshape(1, 3, 3).to(device),
        width,
        height,
        sh_degree=None,
    )
    return rendered[0].cpu().numpy()  # [H, W, channels]


def ghost_fractions(
    rasterize_fn: RasterizeFn,
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    gt_labels,
    removed: Mapping[int, Optional[np.ndarray]],
    views: Sequence[PinholeView],
    gt_maps: Sequence[np.ndarray],
    threshold: float = 0.5,
) -> Dict[int, dict]:
    """Per GT object in ``removed`` (GT id -> indices of the Gaussians its instance removes, None or
    empty: nothing), ``ghost_fraction`` and ``shown_before`` (module doc; None when the object has
    no GT pixel in ``views``), its ``pixels`` and ``ghost_pixels``.

    The Gaussians are activated tensors (linear scales, opacities in [0, 1]) in the frame of the
    views; ``gt_labels`` [N] is each Gaussian's GT object (0 = none); ``gt_maps`` [H, W] per view,
    at whose size each view is rendered; ``rasterize_fn`` has gsplat's ``rasterization`` signature.
    """
    if not 0.0 < threshold < 1.0:
        raise ValueError(f"threshold must be in (0, 1) (got {threshold})")
    if len(views) != len(gt_maps):
        raise ValueError(f"{len(views)} views but {len(gt_maps)} GT maps; pass one GT map per view")
    device = means.device
    labels = torch.as_tensor(np.asarray(gt_labels), device=device).long().reshape(-1)
    if labels.shape[0] != means.shape[0]:
        raise ValueError(f"gt_labels has {labels.shape[0]} entries for {means.shape[0]} Gaussians")
    gaussians = (means, quats, scales, opacities.reshape(-1))
    objects: List[int] = sorted(int(g) for g in removed)
    everything = torch.ones(means.shape[0], dtype=torch.bool, device=device)
    pixels = {g: sum(int((np.asarray(m) == g).sum()) for m in gt_maps) for g in objects}
    shown = {g: 0 for g in objects}
    if objects:
        onehot = (labels[:, None] == torch.tensor(objects, device=device)[None, :]).to(means.dtype)
        for view, gt_map in zip(views, gt_maps):
            weight = _blended(rasterize_fn, gaussians, everything, onehot, view, np.shape(gt_map), device)
            for k, g in enumerate(objects):
                shown[g] += int(((weight[..., k] > threshold) & (np.asarray(gt_map) == g)).sum())
    result: Dict[int, dict] = {}
    for g in objects:
        keep = everything.clone()
        gone = removed[g]
        if gone is not None and len(gone):
            keep[torch.as_tensor(np.asarray(gone), device=device).long()] = False
        channel = (labels == g).to(means.dtype)[:, None]
        ghost = 0
        leftovers = bool((channel[:, 0].bool() & keep).any())  # none left: nothing can show, no render needed
        for view, gt_map in zip(views, gt_maps):
            on_object = np.asarray(gt_map) == g
            if leftovers and on_object.any():  # a view without the object's pixels cannot add a ghost pixel
                weight = _blended(rasterize_fn, gaussians, keep, channel, view, np.shape(gt_map), device)
                ghost += int(((weight[..., 0] > threshold) & on_object).sum())
        result[g] = {
            "pixels": pixels[g],
            "ghost_pixels": ghost,
            "ghost_fraction": ghost / pixels[g] if pixels[g] else None,
            "shown_before": shown[g] / pixels[g] if pixels[g] else None,
        }
    return result


def mean_ghost_percent(per_object: Mapping[int, dict]) -> Optional[float]:
    """Mean ghost fraction over the objects with GT pixels, in percent (None if there are none)."""
    values = [v["ghost_fraction"] for v in per_object.values() if v["ghost_fraction"] is not None]
    return 100.0 * float(np.mean(values)) if values else None
