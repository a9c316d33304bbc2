"""The ``votesplat`` model's options: splatfacto's plus the vote loss, retrofit and viewer ones.

Each field is a ``--pipeline.model.*`` flag of ``ns-train votesplat``. The model itself is
:class:`votesplat_ns.ns.model.VoteSplatModel`; runs' config.yml files name this class by its old
path ``votesplat_ns.ns.model.VoteSplatModelConfig``, which still resolves (re-exported there).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional, Tuple, Type

from nerfstudio.models.splatfacto import SplatfactoModelConfig

from votesplat_ns.core.foreground import DEFAULT_MIN_MASKED_SHARE
from votesplat_ns.core.vote_render import VoteRenderOptions


def _model_class() -> Type:
    # imported when a config is made, not at import: ns/model.py imports this module
    from votesplat_ns.ns.model import VoteSplatModel

    return VoteSplatModel


@dataclass
class VoteSplatModelConfig(SplatfactoModelConfig):
    """splatfacto plus VoteSplat's vote offsets and RVD loss."""

    _target: Type = field(default_factory=_model_class)
    vote_levels: Optional[Tuple[str, ...]] = None
    """Names of the mask levels, one 3D offset per Gaussian per level. Default: the datamanager's levels."""
    vote_loss_weight: float = 1.0
    """lambda_vote: weight of the L1 vote loss (in pixels)."""
    distortion_loss_weight: float = 0.05
    """lambda_d: weight of the vote depth distortion (with l1_pixels: its mean pairwise gap in pixels)."""
    vote_start_step: int = 500
    """Step at which the vote losses start (geometry settles first)."""
    vote_pixels_per_step: int = 4096
    """Pixels with a 2D vote sampled per vote step, shared by all levels (the loss is a mean, so a sample suffices)."""
    vote_every_n_steps: int = 4
    """Run the vote pass every n-th step (1: every step, as the paper, about splatfacto's run time; README.md)."""
    vote_transmittance: float = 0.01
    """Voting transmittance threshold: a Gaussian votes while the transmittance in front of it stays above this."""
    vote_weighting: Literal["uniform", "alpha_t"] = "uniform"
    """Ablation: 'alpha_t' blends votes with alpha*T weights instead of the paper's uniform mean."""
    vote_blend_space: Literal["3d", "2d"] = "3d"
    """Ablation: '2d' projects each Gaussian's vote first, then blends (the paper blends in 3D)."""
    vote_distortion: Literal["l1", "l1_pixels", "squared", "none"] = "l1_pixels"
    """Depth distortion of the votes: l1_pixels (scale-free, chosen on the tuning scenes), the paper's pair sum l1, squared, none."""
    votes_move_geometry: bool = False
    """Let the vote losses move the Gaussians' means/opacities/shapes (off: geometry is the RGB loss's job)."""
    vote_backend: Literal["auto", "torch", "triton"] = "auto"
    """Vote pass: auto (on CUDA the fused Triton losses where the switches allow, else torch code), torch, or triton."""
    retrofit_from: Optional[Path] = None
    """Add instances to a trained scene (a splatfacto run folder, a step-*.ckpt or a 3DGS .ply): train only the vote offsets."""
    retrofit_frame: Literal["auto", "dataparser", "dataset", "colmap"] = "auto"
    """Frame of a --pipeline.model.retrofit-from .ply: dataparser, dataset, colmap, or auto (README: retrofit frames)."""
    retrofit_init: Literal["zero", "lifted"] = "zero"
    """Start of a retrofit's offsets: zero, or lifted (each Gaussian's mask centroids lifted to 3D at its depth, mean over the training views)."""
    foreground_min_masked_share: Optional[float] = DEFAULT_MIN_MASKED_SHARE
    """After training, a Gaussian stays foreground at a level only if more than this share of its weight is in masks (None: all)."""
    clip_model_name: str = "ViT-B-16"
    """open_clip model name used by the viewer's text query box."""
    clip_checkpoint: Optional[Path] = None
    """open_clip weights file for the viewer's text query box (never downloaded); unset disables the box."""

    def vote_render_options(self) -> VoteRenderOptions:
        return VoteRenderOptions(
            weighting=self.vote_weighting,
            blend_space=self.vote_blend_space,
            distortion=self.vote_distortion,
            vote_transmittance=self.vote_transmittance,
            detach_geometry=not self.votes_move_geometry,
            backend=self.vote_backend,
        )
