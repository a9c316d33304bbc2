"""ns-viewer support: the GUI panel of a VoteSplat model (instance overlay, votes picture,
click/text selection, isolate/hide, export), as nerfstudio's viewer finds it.

Three modules, one role each:

1. :mod:`votesplat_ns.ns.viewer_render`: pure image work on tensors (no nerfstudio import):
   :func:`overlay_instances`, :func:`instance_colour_image`, :func:`vote_colours`,
   :func:`display_keep_mask`, :func:`screen_to_pixel`, and the renders :func:`render_rgb`,
   :func:`render_instance_map`, :func:`render_vote_picture` of a :class:`ViewerScene`.
2. :mod:`votesplat_ns.ns.viewer_state`: :class:`InstanceViewerState`, what the person chose plus
   the cached instances and CLIP features; its work happens in ``render_outputs``.
3. This module, :class:`VoteSplatViewerState`: the thin nerfstudio glue. It puts the GUI elements on
   the model (nerfstudio's viewer finds ``ViewerElement``/``ViewerControl`` objects only by walking
   the attributes of the pipeline and of its ``nn.Module`` children) and turns a model and a
   ``Cameras`` into a :class:`ViewerScene` and a :class:`PinholeView`.

The names of the other two modules are re-exported here, where tests and callers import them.
"""

from __future__ import annotations

import threading
import weakref
from pathlib import Path
from typing import TYPE_CHECKING, Any, Dict, Iterable, List, Mapping, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from votesplat_ns.core.cameras import PinholeView
from votesplat_ns.core.instances import InstanceSet
from votesplat_ns.core.scene import Gaussians
from votesplat_ns.ns.run import camera_view, evenly_spaced
from votesplat_ns.ns.viewer_render import DISPLAY_ALL, DISPLAY_MODES, VIEWER_OUTPUTS, ViewerScene
from votesplat_ns.ns.viewer_state import CLIP_DISABLED_HINT, InstanceViewerState

if TYPE_CHECKING:
    from nerfstudio.cameras.cameras import Cameras
    from nerfstudio.viewer.viewer_elements import ViewerClick

MAX_FEATURE_VIEWS = 12
"""Training views used to build per-instance CLIP features in the viewer."""
MAX_FEATURE_VIEW_SIDE = 512
EXPORT_FOLDER_NAME = "votesplat_selections"


def scene_from_model(model: Any) -> ViewerScene:
    """A splatfacto-style model's Gaussians as :class:`ViewerScene` (as its eval render sees them).

    Built from the live tensors each frame rather than through ``TrainedScene.from_model``, which
    copies every parameter to numpy on the CPU and stores degree-0 colours as SH.
    """
    features = torch.cat((model.features_dc[:, None, :], model.features_rest), dim=1)
    if model.config.sh_degree > 0:
        colors, sh_degree = features, min(model.step // model.config.sh_degree_interval, model.config.sh_degree)
    else:
        colors, sh_degree = torch.sigmoid(features).squeeze(1), None
    params = model.gauss_params
    gaussians = Gaussians(
        means=model.means.detach(),
        quats=model.quats.detach(),
        scales=torch.exp(model.scales).detach(),
        opacities=torch.sigmoid(model.opacities).squeeze(-1).detach(),
        colors=colors.detach(),
        sh_degree=sh_degree,
        vote_offsets=params["vote_offsets"].detach() if "vote_offsets" in params else None,
        vote_support=params["vote_support"].detach() if "vote_support" in params else None,
    )
    return ViewerScene(gaussians, model._get_background_color().detach(), model.config.rasterize_mode)


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
            ViewerControl,
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
            cluster_fn=self._run_instances,
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
        # the camera and the viewer handle; splatfacto's compiled get_viewmat needs no warm-up here: it runs with the
        # viewer's interrupt trace suspended (ns/patches.py untraced), whatever thread compiles it first
        model.instance_gui_viewer_control = ViewerControl()

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

    # -------------------------------------------------------------- instances
    def _run_instances(self, scene: ViewerScene, level_names: Sequence[str]) -> InstanceSet:
        """The run's instances (``ns/run_instances.py``), the record the export and the commands read.

        In ns-viewer (and the viewer of ns-train) the pipeline gives the mask check its training views
        and the run folder keeps the record; without a viewer attached (tests) they are computed in memory.
        """
        from nerfstudio.utils.rich_utils import CONSOLE

        from votesplat_ns.core.scene import TrainedScene
        from votesplat_ns.ns.rasterizer import rasterize
        from votesplat_ns.ns.run_instances import InstanceSettings, run_instances

        model = self.model
        if "vote_offsets" not in model.gauss_params:
            raise ValueError(
                "this model has no vote offsets (gauss_params['vote_offsets']); load a votesplat checkpoint"
            )
        trained = TrainedScene.from_model(model, level_names)
        viewer = getattr(model.instance_gui_viewer_control, "viewer", None)
        pipeline = getattr(viewer, "pipeline", None)
        run_dir = Path(viewer.log_filename).parent if viewer is not None else None
        return run_instances(
            trained,
            run_dir,
            InstanceSettings(),
            pipeline,
            rasterize_fn=rasterize,
            log=lambda message: CONSOLE.print(message, soft_wrap=True, markup=False),
        )

    # -------------------------------------------------------------- CLIP
    def _make_encoder(self) -> Any:
        from votesplat_ns.core.semantics import ClipEncoder

        if self.clip_checkpoint is None:  # the panel offers the text query only with a checkpoint
            raise ValueError("the text query needs --pipeline.model.clip-checkpoint (open_clip weights)")
        return ClipEncoder.from_checkpoint(self.clip_model_name, self.clip_checkpoint, device=self.model.device)

    def _feature_views(self) -> List[Tuple[PinholeView, np.ndarray]]:
        viewer = getattr(self.model.instance_gui_viewer_control, "viewer", None)
        if viewer is None:
            raise ValueError("instance features need the training views; open the model in ns-viewer")
        dataset = viewer.pipeline.datamanager.train_dataset
        count = len(dataset)
        if count == 0:
            raise ValueError("the training dataset has no images to build instance features from")
        views = []
        for index in evenly_spaced(count, MAX_FEATURE_VIEWS):
            camera = dataset.cameras[index : index + 1].to(self.model.device)
            image = np.ascontiguousarray(dataset.get_numpy_image(index)[..., :3])
            scale = min(1.0, MAX_FEATURE_VIEW_SIDE / max(int(camera.height.item()), int(camera.width.item())))
            if scale < 1.0:
                camera.rescale_output_resolution(scale)
            view = camera_view(camera)
            if image.shape[:2] != (view.height, view.width):
                from PIL import Image

                image = np.asarray(Image.fromarray(image).resize((view.width, view.height), Image.Resampling.BILINEAR))
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
                    model.crop_box.within(scene.gaussians.means).reshape(-1)
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
