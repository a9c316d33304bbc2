"""One rasterisation entry point for the plugin: gsplat on CUDA, our torch rasteriser on CPU.

splatfacto calls the module-level name ``nerfstudio.models.splatfacto.rasterization``;
:func:`votesplat_ns.ns.patches.install_rasterizer_in_splatfacto` rebinds that name once to
:func:`rasterize`, which
- sends CPU tensors to :func:`votesplat_ns.core.rasterize_torch.rasterize_torch` (gsplat's own
  ``rasterization`` JIT-builds CUDA code and cannot run on CPU), and
- records the cameras it was called with in the returned ``info`` (``info["viewmats"]``,
  ``info["Ks"]``) so the vote pass projects votes with exactly the camera splatfacto used
  (camera optimiser, resolution schedule) without repeating splatfacto's camera code.
"""

from __future__ import annotations

from typing import Any, Dict, Tuple

import torch


def rasterize(means: torch.Tensor, *args: Any, **kwargs: Any) -> Tuple[torch.Tensor, torch.Tensor, Dict[str, Any]]:
    if means.is_cuda:
        from gsplat.rendering import rasterization as gsplat_rasterization

        render, alpha, info = gsplat_rasterization(means, *args, **kwargs)
    else:
        from votesplat_ns.core.rasterize_torch import rasterize_torch

        render, alpha, info = rasterize_torch(means, *args, **kwargs)
    info["viewmats"] = kwargs.get("viewmats", args[4] if len(args) > 4 else None)
    info["Ks"] = kwargs.get("Ks", args[5] if len(args) > 5 else None)
    return render, alpha, info


def project_for_votes(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    tile_size: int = 16,
) -> Dict[str, Any]:
    """Projection and tile lists only: what the vote pass needs, without compositing colours.

    The vote-only path (retrofitting a trained scene, where geometry and appearance are
    frozen) skips the colour pass entirely. Same ``info`` keys and conventions as
    :func:`rasterize` (one camera, not packed, classic opacities).
    """
    import math

    viewmats, Ks = viewmat[None], K[None]
    if means.is_cuda:
        from gsplat.cuda._wrapper import fully_fused_projection, isect_offset_encode, isect_tiles

        radii, means2d, depths, conics, _ = fully_fused_projection(
            means, None, quats, scales, viewmats, Ks, width, height, near_plane=0.01, far_plane=1e10
        )
        tile_width, tile_height = math.ceil(width / tile_size), math.ceil(height / tile_size)
        _, isect_ids, flatten_ids = isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height)
        isect_offsets = isect_offset_encode(isect_ids, 1, tile_width, tile_height)
    else:
        from votesplat_ns.core.rasterize_torch import isect_tiles_torch, project_gaussians_torch

        radii, means2d, depths, conics, _ = project_gaussians_torch(means, quats, scales, viewmats, Ks, width, height)
        tile_width, tile_height = math.ceil(width / tile_size), math.ceil(height / tile_size)
        _, isect_offsets, flatten_ids = isect_tiles_torch(means2d, radii, depths, tile_size, tile_width, tile_height)
    return {
        "means2d": means2d,
        "conics": conics,
        "depths": depths,
        "radii": radii,
        "opacities": opacities[None],
        "isect_offsets": isect_offsets,
        "flatten_ids": flatten_ids,
        "tile_size": tile_size,
        "width": width,
        "height": height,
        "viewmats": viewmats,
        "Ks": Ks,
    }
