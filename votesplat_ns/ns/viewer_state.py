"""The viewer's selection state, without nerfstudio: :class:`InstanceViewerState`.

It records what the person chose (level, selection, display mode, pending click/text query) and
keeps lazily computed, cached results (the instances of every level from clustering the votes,
per-instance CLIP features). Its setters only record state; the work happens in
:meth:`InstanceViewerState.render_outputs`, called from the render with the renders of
:mod:`votesplat_ns.ns.viewer_render`.
"""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, Iterator, Mapping, Optional, Sequence, Set, Tuple, Union

import numpy as np
import torch
from torch import Tensor

from votesplat_ns.core.cameras import PinholeView
from votesplat_ns.core.instances import InstanceSet
from votesplat_ns.ns.viewer_render import (
    DISPLAY_ALL,
    DISPLAY_MODES,
    INSTANCE_OUTPUTS,
    OUTPUT_INSTANCES,
    OUTPUT_OVERLAY,
    OUTPUT_VOTES,
    VIEWER_OUTPUTS,
    RasterizeFn,
    ViewerScene,
    display_keep_mask,
    instance_colour_image,
    overlay_instances,
    render_instance_map,
    render_rgb,
    render_vote_picture,
    screen_to_pixel,
)

CLIP_DISABLED_HINT = "set --pipeline.model.clip-checkpoint to enable"


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


ClusterFn = Callable[[ViewerScene, Sequence[str]], InstanceSet]
EncoderFactory = Callable[[], Any]
FeatureViewsFn = Callable[[], Sequence[Tuple[PinholeView, np.ndarray]]]


def cluster_scene(scene: ViewerScene, level_names: Sequence[str]) -> InstanceSet:
    """Instances of every level from the scene's votes (:func:`votesplat_ns.core.clustering.cluster_levels`)."""
    from votesplat_ns.core.clustering import cluster_levels

    if scene.gaussians.vote_offsets is None:
        raise ValueError("this model has no vote offsets (gauss_params['vote_offsets']); load a votesplat checkpoint")
    support = scene.gaussians.vote_support
    if support is None:
        support = torch.ones(scene.gaussians.vote_offsets.shape[:2])
    return cluster_levels(scene.gaussians.means, scene.gaussians.vote_offsets, support, level_names)


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
    def instances_for(self, scene: ViewerScene) -> InstanceSet:
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

    def instance_ids(self, scene: ViewerScene) -> Tensor:
        """Per-Gaussian ids [N] (-1 none) of the current level, on the scene's device."""
        instances = self.instances_for(scene)
        key = (self.level, str(scene.gaussians.means.device))
        if key not in self._ids_cache:
            self._ids_cache[key] = torch.from_numpy(np.asarray(instances.level(self.level).ids, dtype=np.int64)).to(
                scene.gaussians.means.device
            )
        return self._ids_cache[key]

    def num_instances(self) -> int:
        return 0 if self.instances is None else self.instances.level(self.level).num_instances

    def _instance_features(self, scene: ViewerScene) -> Any:
        from votesplat_ns.core.semantics import instance_features

        if self.level in self._features:
            return self._features[self.level]
        if self.feature_views is None:
            raise ValueError("no training views to build instance features from")
        ids = self.instance_ids(scene)
        if self.encoder_factory is None:
            raise ValueError(f"text queries are off: {CLIP_DISABLED_HINT}")
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
        scene: ViewerScene,
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
        click, query = self._pending_click, self._pending_query
        if ids is not None and click is not None:
            instance_map = render_instance_map(
                scene.subset(keep), view, ids if keep is None else ids[keep], self.rasterize_fn
            )
            self._pending_click = None
            self._resolve_click(instance_map, click)
        if ids is not None and query is not None:
            self._pending_query = None
            self._resolve_query(scene, query)
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

    def _resolve_click(self, instance_map: Tensor, screen_pos: Tuple[float, float]) -> None:
        from votesplat_ns.core.semantics import click_select

        height, width = instance_map.shape
        x, y = screen_to_pixel(screen_pos, width, height)
        self.selected = click_select(instance_map.cpu().numpy(), x, y)
        if self.selected is None:
            self.status = f"clicked the background at pixel ({int(x)}, {int(y)}) of {width}x{height}: nothing selected"
        else:
            self.status = self._selection_status()

    def _resolve_query(self, scene: ViewerScene, text: str) -> None:
        from votesplat_ns.core.semantics import query_text, select_instances

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
        from votesplat_ns.core.ply_io import gaussian_vertex_table, write_gaussian_table

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
        table = gaussian_vertex_table(
            gauss_params["means"],
            gauss_params["features_dc"],
            gauss_params.get("features_rest"),
            gauss_params["opacities"],
            gauss_params["scales"],
            gauss_params["quats"],
        )
        written = write_gaussian_table(path, table, select=indices)
        self.status = f"wrote {path} ({len(written)} Gaussians)"
        return path


def _same_mask(a: Optional[Tensor], b: Optional[Tensor]) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return bool(torch.equal(a, b))
