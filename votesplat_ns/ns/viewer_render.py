"""What the viewer draws, as pure tensor work (no nerfstudio import): instance colours and overlay,
the votes picture, isolate/hide masks, click positions, and the renders of a :class:`ViewerScene`
seen by a :class:`~votesplat_ns.core.cameras.PinholeView`.

Colours come from :func:`votesplat_ns.core.instances.instance_colors`, a pure function of the instance
id, so an instance has the same colour in every view and session (and in the exported pictures).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Callable, Dict, Optional, Sequence, Tuple, Union

import torch
from torch import Tensor

from votesplat_ns.core.cameras import PinholeView
from votesplat_ns.core.instances import instance_colors, render_instance_ids
from votesplat_ns.core.scene import Gaussians

OUTPUT_OVERLAY = "instance_overlay"
OUTPUT_INSTANCES = "instances"
OUTPUT_VOTES = "votes"
VIEWER_OUTPUTS = (OUTPUT_OVERLAY, OUTPUT_INSTANCES, OUTPUT_VOTES)
INSTANCE_OUTPUTS = (OUTPUT_OVERLAY, OUTPUT_INSTANCES)

DISPLAY_ALL = "show all"
DISPLAY_ISOLATE = "isolate selected"
DISPLAY_HIDE = "hide selected"
DISPLAY_MODES = (DISPLAY_ALL, DISPLAY_ISOLATE, DISPLAY_HIDE)

OVERLAY_OPACITY = 0.5
"""Weight of the instance colour in the overlay when nothing is selected."""
SELECTED_OPACITY = 0.8
UNSELECTED_OPACITY = 0.2
"""With a selection, the selected instance is painted strongly and the others faintly."""
VOTE_BACKGROUND_GREY = 0.5
"""Colour of Gaussians without vote supervision at the level (what clustering treats as background)."""
VOTE_COLOUR_QUANTILES = (0.01, 0.99)
"""The vote colour cube spans these quantiles of the foreground votes, so stray votes do not squash it."""
_VOTE_QUANTILE_SAMPLES = 1 << 16


def palette_rgb(instance_ids: Tensor) -> Tensor:
    """Float colours [..., 3] in [0, 1] for instance ids (-1 -> black), on the ids' device."""
    colours = instance_colors(instance_ids.detach().cpu().numpy())
    return torch.from_numpy(colours).to(device=instance_ids.device, dtype=torch.float32) / 255.0


def instance_colour_image(instance_map: Tensor) -> Tensor:
    """The "instances" output: palette colour of each pixel's instance id [H, W] -> [H, W, 3]."""
    _check_instance_map(instance_map)
    return palette_rgb(instance_map)


def overlay_instances(
    rgb: Tensor,
    instance_map: Tensor,
    selected: Optional[int] = None,
    opacity: float = OVERLAY_OPACITY,
    selected_opacity: float = SELECTED_OPACITY,
    unselected_opacity: float = UNSELECTED_OPACITY,
) -> Tensor:
    """The "instance_overlay" output: rgb [H, W, 3] blended with the instance colours.

    A pixel with instance id k >= 0 becomes (1 - a) * rgb + a * palette[k]; pixels with id -1 keep
    rgb. a = ``opacity`` without a selection; with one, a = ``selected_opacity`` on the selected
    instance and ``unselected_opacity`` elsewhere, so the selection stands out.
    """
    _check_instance_map(instance_map)
    if rgb.ndim != 3 or rgb.shape[-1] != 3 or rgb.shape[:2] != instance_map.shape:
        raise ValueError(
            f"rgb must be [H, W, 3] matching the instance map {tuple(instance_map.shape)}, got {tuple(rgb.shape)}"
        )
    for name, value in (
        ("opacity", opacity),
        ("selected_opacity", selected_opacity),
        ("unselected_opacity", unselected_opacity),
    ):
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"{name} must be in [0, 1], got {value}")
    colours = palette_rgb(instance_map).to(rgb.dtype)
    if selected is None:
        weight = torch.full(instance_map.shape, opacity, dtype=rgb.dtype, device=rgb.device)
    else:
        weight = torch.where(instance_map == int(selected), selected_opacity, unselected_opacity).to(rgb.dtype)
    weight = torch.where(instance_map >= 0, weight, torch.zeros_like(weight))[..., None]
    return (1.0 - weight) * rgb + weight * colours


def vote_colours(votes: Tensor, foreground: Optional[Tensor] = None) -> Tensor:
    """Per-Gaussian colours [N, 3] in [0, 1] that picture the votes.

    The colour is the vote position V = p + Δp mapped into the box spanned by the 1st and 99th
    percentiles (per axis) of the foreground votes: Gaussians that vote for the same centre get
    the same colour, so a well-trained instance shows as one flat colour and disagreeing votes as
    a gradient. Gaussians outside ``foreground`` (no vote supervision) or with a non-finite vote
    are grey.
    """
    if votes.ndim != 2 or votes.shape[1] != 3:
        raise ValueError(f"votes must be [N, 3], got {tuple(votes.shape)}")
    finite = torch.isfinite(votes).all(dim=1)
    if foreground is None:
        foreground = finite
    else:
        if foreground.shape != (votes.shape[0],):
            raise ValueError(f"foreground must be [N] = [{votes.shape[0]}], got {tuple(foreground.shape)}")
        foreground = foreground.bool() & finite
    colours = torch.full_like(votes, VOTE_BACKGROUND_GREY, dtype=torch.float32)
    if not bool(foreground.any()):
        return colours
    points = votes[foreground].float()
    stride = max(1, math.ceil(points.shape[0] / _VOTE_QUANTILE_SAMPLES))
    sample = points[::stride]
    quantiles = torch.tensor(VOTE_COLOUR_QUANTILES, device=sample.device, dtype=sample.dtype)
    low, high = torch.quantile(sample, quantiles, dim=0)
    span = high - low
    flat = span <= 1e-12 * (1.0 + low.abs())
    scaled = (points - low) / torch.where(flat, torch.ones_like(span), span)
    scaled = torch.where(flat, torch.full_like(scaled, 0.5), scaled)
    colours[foreground] = scaled.clamp(0.0, 1.0)
    return colours


def display_keep_mask(instance_ids: Tensor, selected: Optional[int], display: str) -> Optional[Tensor]:
    """Which Gaussians the rgb shows: None (all), or bool [N] for isolate / hide of ``selected``."""
    if display not in DISPLAY_MODES:
        raise ValueError(f"display must be one of {DISPLAY_MODES}, got {display!r}")
    if selected is None or display == DISPLAY_ALL:
        return None
    member = instance_ids == int(selected)
    return member if display == DISPLAY_ISOLATE else ~member


def screen_to_pixel(screen_pos: Sequence[float], width: int, height: int) -> Tuple[float, float]:
    """A click's screen position (OpenCV, normalised to [0, 1]) in the continuous pixel frame."""
    if len(screen_pos) != 2:
        raise ValueError(f"screen_pos must be (x, y), got {screen_pos!r}")
    sx, sy = float(screen_pos[0]), float(screen_pos[1])
    if not (math.isfinite(sx) and math.isfinite(sy) and 0.0 <= sx <= 1.0 and 0.0 <= sy <= 1.0):
        raise ValueError(f"screen_pos {screen_pos!r} must be normalised to [0, 1] (OpenCV screen coordinates)")
    # The right/bottom edge (exactly 1.0) belongs to the last pixel.
    x = min(sx * width, math.nextafter(float(width), 0.0))
    y = min(sy * height, math.nextafter(float(height), 0.0))
    return x, y


def _check_instance_map(instance_map: Tensor) -> None:
    if instance_map.ndim != 2 or instance_map.is_floating_point() or instance_map.dtype == torch.bool:
        raise ValueError(
            f"instance map must be an integer [H, W] tensor, got {instance_map.dtype} {tuple(instance_map.shape)}"
        )


@dataclass
class ViewerScene:
    """What the viewer draws: the scene's activated :class:`~votesplat_ns.core.scene.Gaussians`
    (votes included, as the live model holds them) plus how splatfacto draws them, which no scene
    record holds: the ``background`` colour [3] and its ``rasterize_mode``.
    """

    gaussians: Gaussians
    background: Tensor
    rasterize_mode: str = "classic"

    @property
    def num_gaussians(self) -> int:
        return self.gaussians.num_gaussians

    def to(self, device: Union[str, torch.device]) -> "ViewerScene":
        return replace(self, gaussians=self.gaussians.to(device), background=self.background.to(device))

    def subset(self, keep: Optional[Tensor]) -> "ViewerScene":
        return self if keep is None else replace(self, gaussians=self.gaussians.subset(keep))


RasterizeFn = Callable[..., Tuple[Tensor, Tensor, Dict[str, Any]]]


def _default_rasterize() -> RasterizeFn:
    from votesplat_ns.ns.rasterizer import rasterize

    return rasterize


def _background_image(scene: ViewerScene, view: PinholeView) -> Tensor:
    return scene.background.reshape(1, 1, 3).expand(view.height, view.width, 3).to(scene.gaussians.means.dtype).clone()


def _rasterize(
    scene: ViewerScene,
    view: PinholeView,
    colors: Tensor,
    sh_degree: Optional[int],
    render_mode: str,
    rasterize_fn: RasterizeFn,
) -> Tuple[Tensor, Tensor]:
    render, alpha, _ = rasterize_fn(
        scene.gaussians.means,
        scene.gaussians.quats,
        scene.gaussians.scales,
        scene.gaussians.opacities,
        colors,
        viewmats=view.viewmat.reshape(1, 4, 4).to(scene.gaussians.means),
        Ks=view.K.reshape(1, 3, 3).to(scene.gaussians.means),
        width=int(view.width),
        height=int(view.height),
        packed=False,
        near_plane=0.01,
        far_plane=1e10,
        render_mode=render_mode,
        sh_degree=sh_degree,
        sparse_grad=False,
        absgrad=False,
        rasterize_mode=scene.rasterize_mode,
    )
    return render[0], alpha[0]


@torch.no_grad()
def render_rgb(scene: ViewerScene, view: PinholeView, rasterize_fn: Optional[RasterizeFn] = None) -> Dict[str, Tensor]:
    """rgb [H, W, 3], depth [H, W, 1] and accumulation [H, W, 1], exactly as splatfacto's eval render."""
    if scene.num_gaussians == 0:
        return {
            "rgb": _background_image(scene, view).clamp(0.0, 1.0),
            "depth": scene.gaussians.means.new_zeros(view.height, view.width, 1),
            "accumulation": scene.gaussians.means.new_zeros(view.height, view.width, 1),
        }
    render, alpha = _rasterize(
        scene, view, scene.gaussians.colors, scene.gaussians.sh_degree, "RGB+ED", rasterize_fn or _default_rasterize()
    )
    rgb = torch.clamp(render[..., :3] + (1 - alpha) * scene.background.to(render), 0.0, 1.0)
    depth = torch.where(alpha > 0, render[..., 3:4], render[..., 3:4].max())
    return {"rgb": rgb, "depth": depth, "accumulation": alpha}


@torch.no_grad()
def render_instance_map(
    scene: ViewerScene, view: PinholeView, instance_ids: Tensor, rasterize_fn: Optional[RasterizeFn] = None
) -> Tensor:
    """Instance id [H, W] (-1 none) per pixel, by :func:`votesplat_ns.core.instances.render_instance_ids`."""
    if instance_ids.shape != (scene.num_gaussians,):
        raise ValueError(f"instance_ids must be [N] = [{scene.num_gaussians}], got {tuple(instance_ids.shape)}")
    return render_instance_ids(
        rasterize_fn or _default_rasterize(),
        scene.gaussians.means,
        scene.gaussians.quats,
        scene.gaussians.scales,
        scene.gaussians.opacities,
        instance_ids,
        view.viewmat,
        view.K,
        int(view.width),
        int(view.height),
        rasterize_mode=scene.rasterize_mode,
    )


@torch.no_grad()
def render_vote_picture(
    scene: ViewerScene, view: PinholeView, level: int, rasterize_fn: Optional[RasterizeFn] = None
) -> Tensor:
    """The "votes" output [H, W, 3]: :func:`vote_colours` of ``level`` rasterised over the background."""
    if scene.gaussians.vote_offsets is None:
        raise ValueError("this model has no vote offsets (gauss_params['vote_offsets']); load a votesplat checkpoint")
    if not 0 <= level < scene.gaussians.vote_offsets.shape[1]:
        raise ValueError(f"vote level index {level} out of range for {scene.gaussians.vote_offsets.shape[1]} levels")
    if scene.num_gaussians == 0:
        return _background_image(scene, view).clamp(0.0, 1.0)
    foreground = None if scene.gaussians.vote_support is None else scene.gaussians.vote_support[:, level] > 0
    colours = vote_colours(scene.gaussians.means + scene.gaussians.vote_offsets[:, level], foreground).to(
        scene.gaussians.means
    )
    render, alpha = _rasterize(scene, view, colours, None, "RGB", rasterize_fn or _default_rasterize())
    return torch.clamp(render + (1 - alpha) * scene.background.to(render), 0.0, 1.0)
