"""ns-viewer support: instance overlay, votes picture, click/text selection, isolate/hide, export.

Three layers:

1. Pure image work on tensors (no nerfstudio import): :func:`overlay_instances`,
   :func:`instance_colour_image`, :func:`vote_colours`, :func:`display_keep_mask`,
   :func:`screen_to_pixel`, and the renders :func:`render_rgb`, :func:`render_instance_map`,
   :func:`render_vote_picture` of a :class:`SplatScene` seen by a :class:`PinholeView`.
2. :class:`InstanceViewerState`: what the person chose (level, selection, display mode, pending
   click/text query) plus lazily computed, cached results (the instances of every level from
   clustering the votes, per-instance CLIP features). Its setters only record state; the work
   happens in :meth:`InstanceViewerState.render_outputs`, called from the render.
3. :class:`VoteSplatViewerState`: the thin nerfstudio glue. It puts the GUI elements on the model
   (nerfstudio's viewer finds ``ViewerElement``/``ViewerControl`` objects only by walking the
   attributes of the pipeline and of its ``nn.Module`` children) and turns a model and a
   ``Cameras`` into a :class:`SplatScene` and a :class:`PinholeView`.

Colours come from :func:`votesplat_ns.core.instances.instance_colors`, a pure function of the instance
id, so an instance has the same colour in every view and session (and in the exported pictures).
"""

from __future__ import annotations

import contextlib
import math
import sys
import threading
import weakref
from dataclasses import dataclass, replace
from pathlib import Path
from typing import (
    TYPE_CHECKING,
    Any,
    Callable,
    Dict,
    Iterable,
    Iterator,
    List,
    Mapping,
    Optional,
    Sequence,
    Set,
    Tuple,
    Union,
)

import numpy as np
import torch
from torch import Tensor

from votesplat_ns.core.cameras import PinholeView
from votesplat_ns.core.instances import InstanceSet, instance_colors, render_instance_ids
from votesplat_ns.ns.run import camera_view

if TYPE_CHECKING:
    from nerfstudio.cameras.cameras import Cameras
    from nerfstudio.viewer.viewer_elements import ViewerClick

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
MAX_FEATURE_VIEWS = 12
"""Training views used to build per-instance CLIP features in the viewer."""
MAX_FEATURE_VIEW_SIDE = 512
CLIP_DISABLED_HINT = "set --pipeline.model.clip-checkpoint to enable"
EXPORT_FOLDER_NAME = "votesplat_selections"


# ------------------------------------------------------------------------------------------------
# Pure image work


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
class SplatScene:
    """Gaussians ready to rasterise, as splatfacto renders them.

    scales are exp'd, opacities sigmoid'd [N]; ``colors`` are SH coefficients [N, K, 3] with
    ``sh_degree``, or RGB [N, 3] with ``sh_degree=None``; ``background`` [3]. ``vote_offsets``
    [N, L, 3] and ``vote_support`` [N, L] are the model's vote parameters (None if absent).
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    colors: Tensor
    sh_degree: Optional[int]
    background: Tensor
    vote_offsets: Optional[Tensor] = None
    vote_support: Optional[Tensor] = None
    rasterize_mode: str = "classic"

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    def to(self, device: Union[str, torch.device]) -> "SplatScene":
        move = lambda tensor: None if tensor is None else tensor.to(device)  # noqa: E731
        return replace(
            self,
            means=move(self.means),
            quats=move(self.quats),
            scales=move(self.scales),
            opacities=move(self.opacities),
            colors=move(self.colors),
            background=move(self.background),
            vote_offsets=move(self.vote_offsets),
            vote_support=move(self.vote_support),
        )

    def subset(self, keep: Optional[Tensor]) -> "SplatScene":
        if keep is None:
            return self
        pick = lambda tensor: None if tensor is None else tensor[keep]  # noqa: E731
        return replace(
            self,
            means=self.means[keep],
            quats=self.quats[keep],
            scales=self.scales[keep],
            opacities=self.opacities[keep],
            colors=self.colors[keep],
            vote_offsets=pick(self.vote_offsets),
            vote_support=pick(self.vote_support),
        )


RasterizeFn = Callable[..., Tuple[Tensor, Tensor, Dict[str, Any]]]


def _default_rasterize() -> RasterizeFn:
    from votesplat_ns.ns.rasterizer import rasterize

    return rasterize


def _background_image(scene: SplatScene, view: PinholeView) -> Tensor:
    return scene.background.reshape(1, 1, 3).expand(view.height, view.width, 3).to(scene.means.dtype).clone()


def _rasterize(
    scene: SplatScene,
    view: PinholeView,
    colors: Tensor,
    sh_degree: Optional[int],
    render_mode: str,
    rasterize_fn: RasterizeFn,
) -> Tuple[Tensor, Tensor]:
    render, alpha, _ = rasterize_fn(
        scene.means,
        scene.quats,
        scene.scales,
        scene.opacities,
        colors,
        viewmats=view.viewmat.reshape(1, 4, 4).to(scene.means),
        Ks=view.K.reshape(1, 3, 3).to(scene.means),
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
def render_rgb(scene: SplatScene, view: PinholeView, rasterize_fn: Optional[RasterizeFn] = None) -> Dict[str, Tensor]:
    """rgb [H, W, 3], depth [H, W, 1] and accumulation [H, W, 1], exactly as splatfacto's eval render."""
    if scene.num_gaussians == 0:
        return {
            "rgb": _background_image(scene, view).clamp(0.0, 1.0),
            "depth": scene.means.new_zeros(view.height, view.width, 1),
            "accumulation": scene.means.new_zeros(view.height, view.width, 1),
        }
    render, alpha = _rasterize(
        scene, view, scene.colors, scene.sh_degree, "RGB+ED", rasterize_fn or _default_rasterize()
    )
    rgb = torch.clamp(render[..., :3] + (1 - alpha) * scene.background.to(render), 0.0, 1.0)
    depth = torch.where(alpha > 0, render[..., 3:4], render[..., 3:4].max())
    return {"rgb": rgb, "depth": depth, "accumulation": alpha}


@torch.no_grad()
def render_instance_map(
    scene: SplatScene, view: PinholeView, instance_ids: Tensor, rasterize_fn: Optional[RasterizeFn] = None
) -> Tensor:
    """Instance id [H, W] (-1 none) per pixel, by :func:`votesplat_ns.core.instances.render_instance_ids`."""
    if instance_ids.shape != (scene.num_gaussians,):
        raise ValueError(f"instance_ids must be [N] = [{scene.num_gaussians}], got {tuple(instance_ids.shape)}")
    return render_instance_ids(
        rasterize_fn or _default_rasterize(),
        scene.means,
        scene.quats,
        scene.scales,
        scene.opacities,
        instance_ids,
        view.viewmat,
        view.K,
        int(view.width),
        int(view.height),
        rasterize_mode=scene.rasterize_mode,
    )


@torch.no_grad()
def render_vote_picture(
    scene: SplatScene, view: PinholeView, level: int, rasterize_fn: Optional[RasterizeFn] = None
) -> Tensor:
    """The "votes" output [H, W, 3]: :func:`vote_colours` of ``level`` rasterised over the background."""
    if scene.vote_offsets is None:
        raise ValueError("this model has no vote offsets (gauss_params['vote_offsets']); load a votesplat checkpoint")
    if not 0 <= level < scene.vote_offsets.shape[1]:
        raise ValueError(f"vote level index {level} out of range for {scene.vote_offsets.shape[1]} levels")
    if scene.num_gaussians == 0:
        return _background_image(scene, view).clamp(0.0, 1.0)
    foreground = None if scene.vote_support is None else scene.vote_support[:, level] > 0
    colours = vote_colours(scene.means + scene.vote_offsets[:, level], foreground).to(scene.means)
    render, alpha = _rasterize(scene, view, colours, None, "RGB", rasterize_fn or _default_rasterize())
    return torch.clamp(render + (1 - alpha) * scene.background.to(render), 0.0, 1.0)


@contextlib.contextmanager
def _uninterruptible() -> Iterator[None]:
    """Run one-off work (clustering, CLIP features) without the viewer's per-line interrupt trace.

    The viewer renders under ``sys.settrace`` and aborts a render when the camera moves; a
    computation that is cached only when it finishes would otherwise restart on every move.
    """
    previous = sys.gettrace()
    sys.settrace(None)
    try:
        yield
    finally:
        sys.settrace(previous)


# ------------------------------------------------------------------------------------------------
# Viewer state (no nerfstudio)


ClusterFn = Callable[[SplatScene, Sequence[str]], InstanceSet]
EncoderFactory = Callable[[], Any]
FeatureViewsFn = Callable[[], Sequence[Tuple[PinholeView, np.ndarray]]]


def cluster_scene(scene: SplatScene, level_names: Sequence[str]) -> InstanceSet:
    """Instances of every level from the scene's votes (:func:`votesplat_ns.core.clustering.cluster_levels`)."""
    from votesplat_ns.core.clustering import cluster_levels

    if scene.vote_offsets is None:
        raise ValueError("this model has no vote offsets (gauss_params['vote_offsets']); load a votesplat checkpoint")
    support = scene.vote_support
    if support is None:
        support = torch.ones(scene.vote_offsets.shape[:2])
    return cluster_levels(scene.means, scene.vote_offsets, support, level_names)


class InstanceViewerState:
    """What the person picked in the viewer, and the cached instances/features it needs.

    Setters (``set_level``, ``select``, ``set_display``, ``request_click``, ``request_query``,
    ``request_instances``) only record state; :meth:`render_outputs` does the work for one camera.
    Instances are computed lazily (first instance output, click, query, or a request) by
    ``cluster_fn`` on the full scene and cached until the number of Gaussians changes.
    """

    def __init__(
        self,
        level_names: Sequence[str],
        rasterize_fn: Optional[RasterizeFn] = None,
        cluster_fn: ClusterFn = cluster_scene,
        encoder_factory: Optional[EncoderFactory] = None,
        feature_views: Optional[FeatureViewsFn] = None,
    ) -> None:
        level_names = tuple(str(name) for name in level_names)
        if not level_names:
            raise ValueError("the viewer needs at least one vote level name (model.config.vote_levels)")
        self.level_names = level_names
        self.rasterize_fn = rasterize_fn
        self.cluster_fn = cluster_fn
        self.encoder_factory = encoder_factory
        self.feature_views = feature_views
        self.level = level_names[0]
        self.selected: Optional[int] = None
        self.display = DISPLAY_ALL
        self.status = "instances not computed yet"
        self.instances: Optional[InstanceSet] = None
        self._instances_for_n: Optional[int] = None
        self._instances_requested = False
        self._ids_cache: Dict[Tuple[str, str], Tensor] = {}
        self._pending_click: Optional[Tuple[float, float]] = None
        self._pending_query: Optional[str] = None
        self._encoder: Any = None
        self._features: Dict[str, Any] = {}
        self._failure: Optional[Tuple[int, str]] = None
        self._announce = False  # say how many instances the level has at the next render
        self.cluster_calls = 0

    # -------------------------------------------------------------- setters (state only)
    @property
    def level_index(self) -> int:
        return self.level_names.index(self.level)

    def set_level(self, level: str) -> None:
        if level not in self.level_names:
            raise ValueError(f"unknown vote level {level!r}; pick one of {list(self.level_names)}")
        if level != self.level:
            self.level = level
            self.selected = None  # ids of different levels are unrelated
            self._announce = True

    def select(self, instance_id: Optional[int]) -> None:
        """Select an instance id at the current level (None or a negative id clears the selection)."""
        self.selected = None if instance_id is None or int(instance_id) < 0 else int(instance_id)

    def set_display(self, display: str) -> None:
        if display not in DISPLAY_MODES:
            raise ValueError(f"display must be one of {DISPLAY_MODES}, got {display!r}")
        self.display = display

    def request_instances(self) -> None:
        """Recompute the instances at the next render (the "Compute instances" button)."""
        self._instances_requested = True

    def request_click(self, screen_pos: Sequence[float]) -> None:
        """Select the instance under ``screen_pos`` (normalised OpenCV screen coordinates) at the next render."""
        screen_to_pixel(screen_pos, 1, 1)  # validate now, where the caller can see the error
        self._pending_click = (float(screen_pos[0]), float(screen_pos[1]))

    def request_query(self, text: str) -> None:
        """Select the instance that best matches ``text`` at the next render (needs an encoder)."""
        self._pending_query = text.strip() or None

    @property
    def has_encoder(self) -> bool:
        return self.encoder_factory is not None

    # -------------------------------------------------------------- cached results
    def instances_for(self, scene: SplatScene) -> InstanceSet:
        """The instances of ``scene`` (the full model, not a crop), clustering if needed."""
        stale = self.instances is None or self._instances_for_n != scene.num_gaussians
        if stale or self._instances_requested:
            failed = self._failure
            if failed is not None and failed[0] == scene.num_gaussians and not self._instances_requested:
                raise ValueError(failed[1])  # the same model fails the same way: do not re-cluster every frame
            self._instances_requested = False
            self.cluster_calls += 1
            try:
                with _uninterruptible():
                    instances = self.cluster_fn(scene, self.level_names)
                if instances.num_gaussians != scene.num_gaussians:
                    raise ValueError(
                        f"clustering returned ids for {instances.num_gaussians} Gaussians, the scene has {scene.num_gaussians}"
                    )
            except ValueError as error:
                self._failure = (scene.num_gaussians, str(error))
                raise
            self.instances, self._instances_for_n, self._failure = instances, scene.num_gaussians, None
            self._ids_cache.clear()
            self._features.clear()
            self._announce = True
        assert self.instances is not None
        return self.instances

    def instance_ids(self, scene: SplatScene) -> Tensor:
        """Per-Gaussian ids [N] (-1 none) of the current level, on the scene's device."""
        instances = self.instances_for(scene)
        key = (self.level, str(scene.means.device))
        if key not in self._ids_cache:
            self._ids_cache[key] = torch.from_numpy(np.asarray(instances.level(self.level).ids, dtype=np.int64)).to(
                scene.means.device
            )
        return self._ids_cache[key]

    def num_instances(self) -> int:
        return 0 if self.instances is None else self.instances.level(self.level).num_instances

    def _instance_features(self, scene: SplatScene) -> Any:
        from votesplat_ns.core.semantics import instance_features

        if self.level in self._features:
            return self._features[self.level]
        if self.feature_views is None:
            raise ValueError("no training views to build instance features from")
        ids = self.instance_ids(scene)
        with _uninterruptible():
            if self._encoder is None:
                self._encoder = self.encoder_factory()
            images, maps = [], []
            for view, image in self.feature_views():
                images.append(np.ascontiguousarray(image[..., :3]))
                maps.append(render_instance_map(scene, view, ids, self.rasterize_fn).cpu().numpy())
            features = instance_features(images, maps, self._encoder)
        if len(features) == 0:
            raise ValueError("no instance is visible in the training views with enough pixels to describe it")
        self._features[self.level] = features
        return features

    # -------------------------------------------------------------- the render
    def needs_render(self, wanted: Set[str]) -> bool:
        """Whether :meth:`render_outputs` has anything to do for these outputs."""
        return bool(wanted) or self._needs_instances(wanted)

    def _needs_instances(self, wanted: Set[str]) -> bool:
        return (
            bool(wanted & set(INSTANCE_OUTPUTS))
            or self._instances_requested
            or self._pending_click is not None
            or self._pending_query is not None
            or (self.selected is not None and self.display != DISPLAY_ALL)
        )

    def render_outputs(
        self,
        scene: SplatScene,
        view: PinholeView,
        base_outputs: Mapping[str, Tensor],
        wanted: Iterable[str] = VIEWER_OUTPUTS,
        crop: Optional[Tensor] = None,
    ) -> Dict[str, Tensor]:
        """The viewer outputs in ``wanted`` for one camera, plus rgb/depth/accumulation when isolating/hiding.

        ``scene`` is the whole model; ``crop`` (bool [N]) the Gaussians inside the viewer's crop
        box; ``base_outputs["rgb"]`` the model's own render of this camera. Pending clicks and
        text queries are resolved first, so the frame already shows their selection.
        """
        wanted = set(wanted)
        unknown = wanted - set(VIEWER_OUTPUTS)
        if unknown:
            raise ValueError(f"unknown viewer outputs {sorted(unknown)}; choose from {VIEWER_OUTPUTS}")
        outputs: Dict[str, Tensor] = {}
        ids = None
        if self._needs_instances(wanted):
            try:
                ids = self.instance_ids(scene)
                if self._announce:
                    self.status, self._announce = f"{self.num_instances()} instances at level '{self.level}'", False
            except ValueError as error:
                self.status = f"no instances: {error}"
                self._pending_click = self._pending_query = None
                self._instances_requested = False
        if self.instances is not None and self.selected is not None and self.selected >= self.num_instances():
            self.status = (
                f"level '{self.level}' has instances 0..{self.num_instances() - 1}; no instance {self.selected}"
            )
            self.selected = None

        def visible(selected: Optional[int]) -> Optional[Tensor]:
            keep = None if ids is None else display_keep_mask(ids, selected, self.display)
            if crop is not None:
                keep = crop if keep is None else keep & crop
            return keep

        keep = visible(self.selected)
        instance_map = None
        if ids is not None and self._pending_click is not None:
            instance_map = render_instance_map(
                scene.subset(keep), view, ids if keep is None else ids[keep], self.rasterize_fn
            )
            self._resolve_click(instance_map)
        if ids is not None and self._pending_query is not None:
            self._resolve_query(scene)
        new_keep = visible(self.selected)
        if not _same_mask(keep, new_keep):
            keep, instance_map = new_keep, None
        shown = scene.subset(keep)

        rgb = base_outputs["rgb"]
        if ids is not None and self.selected is not None and self.display != DISPLAY_ALL:
            outputs.update(render_rgb(shown, view, self.rasterize_fn))
            rgb = outputs["rgb"]
        if ids is not None and wanted & set(INSTANCE_OUTPUTS):
            if instance_map is None:
                instance_map = render_instance_map(shown, view, ids if keep is None else ids[keep], self.rasterize_fn)
            if OUTPUT_OVERLAY in wanted:
                outputs[OUTPUT_OVERLAY] = overlay_instances(rgb, instance_map, self.selected)
            if OUTPUT_INSTANCES in wanted:
                outputs[OUTPUT_INSTANCES] = instance_colour_image(instance_map)
        elif wanted & set(INSTANCE_OUTPUTS):
            for name in wanted & set(INSTANCE_OUTPUTS):
                outputs[name] = rgb  # no instances (status says why): show the plain render
        if OUTPUT_VOTES in wanted:
            try:
                outputs[OUTPUT_VOTES] = render_vote_picture(shown, view, self.level_index, self.rasterize_fn)
            except ValueError as error:
                self.status = f"no votes: {error}"
                outputs[OUTPUT_VOTES] = rgb
        return outputs

    def _resolve_click(self, instance_map: Tensor) -> None:
        from votesplat_ns.core.semantics import click_select

        screen_pos, self._pending_click = self._pending_click, None
        height, width = instance_map.shape
        x, y = screen_to_pixel(screen_pos, width, height)
        self.selected = click_select(instance_map.cpu().numpy(), x, y)
        if self.selected is None:
            self.status = f"clicked the background at pixel ({int(x)}, {int(y)}) of {width}x{height}: nothing selected"
        else:
            self.status = self._selection_status()

    def _resolve_query(self, scene: SplatScene) -> None:
        from votesplat_ns.core.semantics import query_text, select_instances

        text, self._pending_query = self._pending_query, None
        if not self.has_encoder:
            self.status = f"text queries are off: {CLIP_DISABLED_HINT}"
            return
        try:
            ranked = query_text(text, self._instance_features(scene), self._encoder)
        except ValueError as error:
            self.status = f"query failed: {error}"
            return
        self.selected = select_instances(ranked)[0]
        self.status = f"'{text}': {self._selection_status()} (relevancy {ranked[0][1]:.2f})"

    def _selection_status(self) -> str:
        count = int(self.instances.level(self.level).counts[self.selected]) if self.instances is not None else 0
        return f"selected instance {self.selected} at level '{self.level}' ({count} Gaussians)"

    # -------------------------------------------------------------- export
    def export_selected(self, gauss_params: Mapping[str, Tensor], folder: Union[str, Path]) -> Path:
        """Write the selected instance's Gaussians as a standard 3DGS PLY into ``folder``; returns its path.

        ``gauss_params`` holds splatfacto's raw parameters (means, features_dc, features_rest,
        opacities as logits, scales as logs, quats) of the scene the instances were computed for.
        """
        from votesplat_ns.core.ply_io import write_gaussian_ply

        if self.instances is None or self.selected is None:
            raise ValueError("nothing selected: compute instances and click an instance (or type a query) first")
        n = int(gauss_params["means"].shape[0])
        if n != self.instances.num_gaussians:
            raise ValueError(
                f"the model has {n} Gaussians but the instances were computed for {self.instances.num_gaussians}; "
                "press 'Compute instances' again"
            )
        indices = self.instances.level(self.level).gaussian_indices(self.selected)
        folder = Path(folder)
        if folder.exists() and not folder.is_dir():
            raise ValueError(f"export folder {folder} is a file; remove it or choose another folder")
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"{self.level}_instance_{self.selected:03d}.ply"
        written = write_gaussian_ply(
            path,
            gauss_params["means"],
            gauss_params["features_dc"],
            gauss_params.get("features_rest"),
            gauss_params["opacities"],
            gauss_params["scales"],
            gauss_params["quats"],
            select=indices,
        )
        self.status = f"wrote {path} ({len(written)} Gaussians)"
        return path


def _same_mask(a: Optional[Tensor], b: Optional[Tensor]) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return bool(torch.equal(a, b))


# ------------------------------------------------------------------------------------------------
# nerfstudio glue


def scene_from_model(model: Any) -> SplatScene:
    """A splatfacto-style model's Gaussians as :class:`SplatScene` (as its eval render sees them)."""
    features = torch.cat((model.features_dc[:, None, :], model.features_rest), dim=1)
    if model.config.sh_degree > 0:
        colors, sh_degree = features, min(model.step // model.config.sh_degree_interval, model.config.sh_degree)
    else:
        colors, sh_degree = torch.sigmoid(features).squeeze(1), None
    params = model.gauss_params
    return SplatScene(
        means=model.means.detach(),
        quats=model.quats.detach(),
        scales=torch.exp(model.scales).detach(),
        opacities=torch.sigmoid(model.opacities).squeeze(-1).detach(),
        colors=colors.detach(),
        sh_degree=sh_degree,
        background=model._get_background_color().detach(),
        vote_offsets=params["vote_offsets"].detach() if "vote_offsets" in params else None,
        vote_support=params["vote_support"].detach() if "vote_support" in params else None,
        rasterize_mode=model.config.rasterize_mode,
    )


def _viewer_control_class() -> type:
    from nerfstudio.viewer.viewer_elements import ViewerControl

    class VoteSplatViewerControl(ViewerControl):
        """nerfstudio's ViewerControl, plus compiling splatfacto's ``get_viewmat`` when the viewer attaches.

        ``get_viewmat`` is ``torch.compile``'d and compiles on its first call. If that call is the
        first viewer render, the viewer's per-line interrupt trace can fire inside dynamo (the
        camera moved); dynamo turns it into an InternalTorchDynamoError that kills the render
        thread and the page never updates again. ``_setup`` runs in the main thread before any
        render thread starts, so compiling there (as the renders call it: no grad, float32) is safe.
        """

        def _setup(self, viewer: Any) -> None:
            super()._setup(viewer)
            from nerfstudio.models import splatfacto

            device = viewer.get_model().device
            with torch.no_grad():
                splatfacto.get_viewmat(torch.eye(4, device=device)[None, :3, :])

    return VoteSplatViewerControl


class VoteSplatViewerState:
    """ns-viewer controls for a VoteSplat model (instances, selection, text query, export).

    Construct it in ``populate_modules``; it adds its GUI elements to the model as attributes
    (nerfstudio lays out custom elements in the alphabetical order of the attribute names, hence
    the numbered ``instance_gui_*`` names). ``extra_outputs`` adds the viewer outputs to the
    model's outputs, but only for renders made by the viewer's render threads, so training, eval
    and ``ns-render`` outputs are unchanged and cost nothing.
    """

    def __init__(self, model: Any) -> None:
        from nerfstudio.viewer.viewer_elements import (
            ViewerButton,
            ViewerCheckbox,
            ViewerDropdown,
            ViewerNumber,
            ViewerText,
        )

        self._model = weakref.ref(model)
        config = model.config
        self.clip_checkpoint = getattr(config, "clip_checkpoint", None)
        self.clip_model_name = getattr(config, "clip_model_name", "ViT-B-16")
        self.state = InstanceViewerState(
            config.vote_levels,
            rasterize_fn=None,
            encoder_factory=self._make_encoder if self.clip_checkpoint else None,
            feature_views=self._feature_views,
        )
        self._shown_status = None
        self._shown_selection: Optional[int] = None
        levels = list(self.state.level_names)

        model.instance_gui_0_level = ViewerDropdown(
            "Instance level",
            levels[0],
            levels,
            cb_hook=self._on_level,
            hint="vote level (hierarchy) the instances come from",
        )
        model.instance_gui_1_compute = ViewerButton(
            "Compute instances", cb_hook=lambda _: self.state.request_instances()
        )
        model.instance_gui_2_click = ViewerCheckbox(
            "Click to select",
            False,
            cb_hook=self._on_click_mode,
            hint="click the render to select the instance under the cursor",
        )
        model.instance_gui_3_selected = ViewerNumber(
            "Selected instance",
            -1,
            cb_hook=self._on_selected_number,
            hint="instance id at the current level; -1 = none",
        )
        model.instance_gui_4_display = ViewerDropdown(
            "Selected instance display",
            DISPLAY_ALL,
            list(DISPLAY_MODES),
            cb_hook=lambda e: self.state.set_display(e.value),
        )
        if self.clip_checkpoint:
            model.instance_gui_5_query = ViewerText(
                "Text query",
                "",
                cb_hook=lambda e: self.state.request_query(e.value),
                hint="open-vocabulary query (CLIP)",
            )
        else:
            model.instance_gui_5_query = ViewerText(
                "Text query", CLIP_DISABLED_HINT, disabled=True, hint=CLIP_DISABLED_HINT
            )
        model.instance_gui_6_export = ViewerButton("Export selected instance (PLY)", cb_hook=self._on_export)
        model.instance_gui_7_status = ViewerText("Status", self.state.status, disabled=True)
        model.instance_gui_viewer_control = _viewer_control_class()()

    # -------------------------------------------------------------- callbacks (state only)
    @property
    def model(self) -> Any:
        model = self._model()
        if model is None:
            raise ValueError("the model this viewer state belongs to no longer exists")
        return model

    def _on_level(self, element: Any) -> None:
        self.state.set_level(element.value)

    def _on_selected_number(self, element: Any) -> None:
        self.state.select(int(element.value))

    def _on_click_mode(self, element: Any) -> None:
        control = self.model.instance_gui_viewer_control
        if not hasattr(control, "viser_server"):
            return  # no viewer attached
        if element.value:
            control.register_pointer_cb("click", self._on_click)
        else:
            control.unregister_pointer_cb()

    def _on_click(self, click: "ViewerClick") -> None:
        self.state.request_click(click.screen_pos)
        viewer = getattr(self.model.instance_gui_viewer_control, "viewer", None)
        if viewer is not None:
            viewer._trigger_rerender()

    def _on_export(self, _: Any) -> None:
        viewer = getattr(self.model.instance_gui_viewer_control, "viewer", None)
        run_folder = (
            Path(viewer.log_filename).parent if viewer is not None else Path.cwd()
        )  # the run's config.yml is there
        folder = run_folder.resolve() / EXPORT_FOLDER_NAME
        try:
            self.state.export_selected({k: v.detach() for k, v in self.model.gauss_params.items()}, folder)
        except ValueError as error:
            self.state.status = f"export failed: {error}"
        self._show_state()

    # -------------------------------------------------------------- CLIP
    def _make_encoder(self) -> Any:
        from votesplat_ns.core.semantics import ClipEncoder

        return ClipEncoder.from_checkpoint(self.clip_model_name, self.clip_checkpoint, device=self.model.device)

    def _feature_views(self) -> List[Tuple[PinholeView, np.ndarray]]:
        viewer = getattr(self.model.instance_gui_viewer_control, "viewer", None)
        if viewer is None:
            raise ValueError("instance features need the training views; open the model in ns-viewer")
        dataset = viewer.pipeline.datamanager.train_dataset
        count = len(dataset)
        if count == 0:
            raise ValueError("the training dataset has no images to build instance features from")
        chosen = min(count, MAX_FEATURE_VIEWS)
        picks = sorted({round(i * (count - 1) / max(1, chosen - 1)) for i in range(chosen)})  # evenly spread
        views = []
        for index in picks:
            camera = dataset.cameras[index : index + 1].to(self.model.device)
            image = np.ascontiguousarray(dataset.get_numpy_image(index)[..., :3])
            scale = min(1.0, MAX_FEATURE_VIEW_SIDE / max(int(camera.height.item()), int(camera.width.item())))
            if scale < 1.0:
                camera.rescale_output_resolution(scale)
            view = camera_view(camera)
            if image.shape[:2] != (view.height, view.width):
                from PIL import Image

                image = np.asarray(Image.fromarray(image).resize((view.width, view.height), Image.BILINEAR))
            views.append((view, image))
        return views

    # -------------------------------------------------------------- render
    def extra_outputs(self, camera: "Cameras", outputs: Mapping[str, Tensor]) -> Dict[str, Tensor]:
        """Viewer outputs for a render made by ns-viewer's render thread; {} for any other caller.

        Only the outputs on screen (the "Output type" and, when split, the split output) are
        computed; the others are listed with the rgb as their image so the dropdown keeps them.
        """
        from nerfstudio.viewer.render_state_machine import RenderStateMachine

        thread = threading.current_thread()
        if not isinstance(thread, RenderStateMachine):
            return {}
        panel = thread.viewer.control_panel
        wanted = {panel.output_render}
        if panel.split:
            wanted.add(panel.split_output_render)
        return self.viewer_outputs(camera, outputs, wanted & set(VIEWER_OUTPUTS))

    def viewer_outputs(
        self, camera: "Cameras", outputs: Mapping[str, Tensor], wanted: Iterable[str]
    ) -> Dict[str, Tensor]:
        """Every viewer output name, with ``wanted`` ones computed for ``camera`` (others alias rgb)."""
        model = self.model
        wanted = set(wanted)
        extra: Dict[str, Tensor] = {}
        if self.state.needs_render(wanted):
            with torch.no_grad():
                scene = scene_from_model(model)
                crop = (
                    model.crop_box.within(scene.means).reshape(-1)
                    if getattr(model, "crop_box", None) is not None
                    else None
                )
                extra = self.state.render_outputs(scene, self._view(camera), outputs, wanted, crop)
        rgb = extra.get("rgb", outputs["rgb"])
        for name in VIEWER_OUTPUTS:
            extra.setdefault(name, rgb)
        self._show_state()
        return extra

    @staticmethod
    def _view(camera: "Cameras") -> PinholeView:
        if camera.shape[0] != 1:
            raise ValueError(f"the viewer renders one camera at a time, got {camera.shape[0]}")
        return camera_view(camera)

    def _show_state(self) -> None:
        """Mirror state changes made during a render (selection, status) into the GUI."""
        model = self.model
        if self.state.status != self._shown_status:
            self._shown_status = self.state.status
            model.instance_gui_7_status.value = self.state.status
        selected = -1 if self.state.selected is None else self.state.selected
        if selected != self._shown_selection:
            self._shown_selection = selected
            if int(model.instance_gui_3_selected.value) != selected:
                model.instance_gui_3_selected.value = selected
