"""The Gaussians a retrofit (``--pipeline.model.retrofit-from``) starts from: a trained run's checkpoint or
a standard 3DGS PLY, checked against the model's settings and, for a PLY, moved into the training frame
(:func:`votesplat_ns.ns.retrofit.resolve_frame`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, Optional, Tuple

import torch
from nerfstudio.utils.rich_utils import CONSOLE

from votesplat_ns.core.ply_io import VOTESPLAT_OFFSET_PROPERTIES, GaussianPlyError, read_3dgs_ply, read_ply_header
from votesplat_ns.errors import VoteSplatInputError
from votesplat_ns.ns.rasterizer import rasterize
from votesplat_ns.ns.retrofit import resolve_frame
from votesplat_ns.ns.run import gaussians_from_ply_arrays, latest_checkpoint, load_gaussians, splatfacto_dc_from_ply

FLAG = "--pipeline.model.retrofit-from"


def retrofit_gaussians(
    source: Path, sh_degree: int, frame_option: str, model_kwargs: Dict[str, Any], features_rest_shape: Tuple[int, ...]
) -> Optional[Tuple[Dict[str, torch.Tensor], Optional[str]]]:
    """(splatfacto's Gaussian parameters on CPU, the PLY's frame or None for a checkpoint), or None when there
    is nothing to load now (the path does not exist yet, or a trained run is being loaded whose own
    checkpoint follows). ``model_kwargs``: the model's construction kwargs (metadata, device);
    ``features_rest_shape``: the model's [K, 3] per Gaussian."""
    if not source.exists():
        # Fine when a trained retrofit run is being loaded (its own checkpoint follows);
        # ns-train stops in the model's get_training_callbacks with a clear message.
        return None
    frame: Optional[str] = None
    if source.suffix.lower() == ".ply":
        loaded = _gaussians_from_ply(source, sh_degree, frame_option, model_kwargs)
        if loaded is None:
            return None
        gaussians, frame = loaded
    else:
        gaussians = load_gaussians(latest_checkpoint(source))
    if tuple(gaussians["features_rest"].shape[1:]) != tuple(features_rest_shape):
        raise VoteSplatInputError(
            f"{source} has SH features of shape {tuple(gaussians['features_rest'].shape[1:])}, the model expects "
            f"{tuple(features_rest_shape)}: pass the --pipeline.model.sh-degree it was trained with"
        )
    return gaussians, frame


def _gaussians_from_ply(
    source: Path, sh_degree: int, frame_option: str, model_kwargs: Dict[str, Any]
) -> Optional[Tuple[Dict[str, torch.Tensor], str]]:
    """The Gaussians of a 3DGS PLY, checked and moved into the training frame (None: a checkpoint will follow)."""
    make_reference = (model_kwargs.get("metadata") or {}).get("retrofit_reference")
    if make_reference is None:
        raise VoteSplatInputError(
            f"{FLAG} {source}: a PLY needs votesplat's datamanager, whose cameras and images tell the PLY's frame"
        )
    reference = make_reference()
    if reference.test_mode != "val":
        return None  # a trained run is loaded to evaluate, view or export it: its checkpoint replaces the Gaussians
    try:
        arrays, ply_sh_degree = read_3dgs_ply(source)
    except GaussianPlyError as err:
        raise VoteSplatInputError(f"{FLAG} {err}") from None
    if set(VOTESPLAT_OFFSET_PROPERTIES) & {name for name, _ in read_ply_header(source)[2]}:
        CONSOLE.print(
            f"Note: {source} holds vote offsets (vote_offset_0..2, as the official VoteSplat code writes them); they "
            "are not read: the retrofit learns its own (--pipeline.model.retrofit-init)",
            soft_wrap=True,
            markup=False,
        )
    if ply_sh_degree != sh_degree:
        raise VoteSplatInputError(
            f"{FLAG} {source} has SH degree {ply_sh_degree} ({arrays['features_rest'].shape[1] * 3} f_rest properties), "
            f"the model is set to {sh_degree}: pass --pipeline.model.sh-degree {ply_sh_degree}"
        )
    device = torch.device(model_kwargs.get("device") or "cpu")
    gaussians = {name: value.to(device) for name, value in gaussians_from_ply_arrays(arrays).items()}
    frame, moved, fits = resolve_frame(gaussians, reference, frame_option, source, rasterize, ply_sh_degree)
    moved["features_dc"] = splatfacto_dc_from_ply(moved["features_dc"], ply_sh_degree)
    fit = next(f for f in fits if frame == f.name or frame in f.same_as)
    CONSOLE.log(
        f"Retrofit from {source}: {moved['means'].shape[0]} Gaussians in frame '{frame}' "
        f"({fit.in_view_share:.1%} in the training views, {fit.psnr:.1f} dB PSNR at {len(reference.views()[1])} views)"
    )
    return {name: value.cpu() for name, value in moved.items()}, frame
