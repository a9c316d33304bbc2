"""``ns-export votesplat-instances`` / ``votesplat export``: the command's options and its run on a trained run.

The writing itself (folder layout, what is replaced) is :func:`votesplat_ns.ns.instance_export.export_instances`;
the hook that adds the subcommand to ``ns-export`` is in :mod:`votesplat_ns.ns.patches`.

This module keeps nerfstudio imports inside functions: the plugin's method entry point imports it
(through the ``ns-export`` hook) while nerfstudio is still importing its method configs.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, List, Literal, Optional, Tuple

import torch

from votesplat_ns.core.cameras import PinholeView
from votesplat_ns.core.clustering import DEFAULT_MAX_POINTS, ClusteringOptions
from votesplat_ns.errors import one_line_errors, writing_into
from votesplat_ns.ns.instance_export import check_output_dir, export_instances
from votesplat_ns.ns.mask_views import DEFAULT_MASK_VIEWS
from votesplat_ns.ns.run import DatasetMissing, camera_view, evenly_spaced, load_run, load_run_scene
from votesplat_ns.ns.run_instances import InstanceSettings, run_instances


def training_views(pipeline, num_views: int, max_width: int = 320) -> List[PinholeView]:
    """Up to ``num_views`` evenly spaced training cameras (and images), at most ``max_width`` wide."""
    if num_views <= 0:
        return []
    dataset = pipeline.datamanager.train_dataset
    cameras = dataset.cameras
    count = len(cameras)
    views = []
    for index in evenly_spaced(count, num_views):
        view = camera_view(cameras, index)
        width, height = view.width, view.height
        scale = min(1.0, max_width / width)
        K = view.K.clone()
        K[:2] *= scale
        out_w, out_h = max(1, int(round(width * scale))), max(1, int(round(height * scale)))
        image = None
        with contextlib.suppress(Exception):  # the picture still works without the photo row
            image = dataset[index]["image"][..., :3].float()
            image = torch.nn.functional.interpolate(image.permute(2, 0, 1)[None], size=(out_h, out_w), mode="area")[
                0
            ].permute(1, 2, 0)
        views.append(PinholeView(view.viewmat, K, out_w, out_h, image=image))
    return views


def default_rasterizer() -> Optional[Callable[..., tuple]]:
    """The plugin's rasteriser entry point (gsplat on CUDA tensors, pure torch on CPU tensors)."""
    try:
        from votesplat_ns.ns.rasterizer import rasterize
    except ImportError:
        return None
    return rasterize


@dataclass
class ExportVoteSplatInstances:
    """Cluster a VoteSplat model's 3D votes into instances and export one 3DGS PLY per instance,
    the background, the whole scene with per-vertex instance ids, optional object removal and an
    instances.json manifest."""

    load_config: Path
    """Path to the config YAML file."""
    output_dir: Path
    """Path to the output directory (created; replaced only if empty or a previous instance export)."""
    level: Optional[str] = None
    """Vote level whose instances get one PLY each, by name or index (default: the first level)."""
    remove: Tuple[int, ...] = ()
    """Instance ids of that level to remove from the scene (writes scene_without_<ids>.ply)."""
    min_cluster_size: Optional[int] = None
    """Smallest instance, in Gaussians (default: 0.05 percent of the foreground Gaussians, at least 10)."""
    min_samples: Optional[int] = None
    """HDBSCAN min_samples, in clustered (subsampled) votes (default: min(10, scaled min_cluster_size))."""
    max_points: int = DEFAULT_MAX_POINTS
    """Most votes HDBSCAN clusters; the others take the label of their nearest clustered vote."""
    noise: Literal["nearest", "drop"] = "nearest"
    """Noise votes: 'nearest' joins them to the nearest instance within noise-radius, 'drop' keeps them out."""
    noise_radius: Optional[float] = None
    """Distance for the 'nearest' noise rule, in scene units (default: 2 percent of the vote spread)."""
    cluster_selection_epsilon: float = 0.0
    """HDBSCAN cluster_selection_epsilon: merge clusters closer than this (scene units)."""
    seed: int = 0
    """Seed of the clustering subsample (same seed, same instances)."""
    num_views: int = 4
    """Training views drawn in instances.png (0: no picture)."""
    picture_width: int = 320
    """Width in pixels of each view in instances.png."""
    mask_check: bool = True
    """Check the instances against the run's training masks (votesplat_ns/core/mask_consensus.py): split off
    Gaussians that lie in another object's mask, merge clusters that the masks cover together, drop clusters that lie
    in no mask. Needs the run's dataset and masks (as at training); off: the vote clustering alone."""
    mask_check_views: int = DEFAULT_MASK_VIEWS
    """Training views the mask check looks through (evenly spaced)."""
    data: Optional[Path] = None
    """Dataset folder, if it moved since training (default: the one in the config). Without the dataset the
    export still writes the PLY files: the vote clustering without the mask check, and no instances.png."""

    def clustering(self) -> ClusteringOptions:
        """The HDBSCAN flags as :func:`cluster_levels` settings."""
        return ClusteringOptions(
            **{name: getattr(self, name) for name in ClusteringOptions.__dataclass_fields__ if hasattr(self, name)}
        )

    def instance_settings(self) -> InstanceSettings:
        """The settings of the run's instances (the record every command reads, ``ns/run_instances.py``)."""
        return InstanceSettings.make(self.clustering(), self.mask_check, self.mask_check_views)

    def main(self) -> None:
        from nerfstudio.utils.rich_utils import CONSOLE

        # bad input (ValueError, VoteSplatInputError) ends the command with one line, exit 1
        with one_line_errors(catch=(ValueError,)), writing_into(self.output_dir, "--output-dir"):
            check_output_dir(self.output_dir, "--output-dir")  # before the checkpoint is loaded
            settings = self.instance_settings()  # its flags too
            missing: Optional[str] = None
            try:
                pipeline, scene, _ = load_run(self.load_config, data=self.data)
            except DatasetMissing as error:  # the PLY files need the checkpoint alone
                pipeline, missing = None, error.reason
                scene, _ = load_run_scene(self.load_config)
            device = torch.device(scene.device)
            views: List[PinholeView] = []
            rasterize_fn = default_rasterizer() if self.num_views > 0 else None
            if rasterize_fn is None and self.num_views > 0:
                CONSOLE.print("[yellow]No rasterizer available on this device; instances.png is skipped.")
            elif missing is not None and self.num_views > 0:
                CONSOLE.print(
                    f"Training views unavailable ({missing}); instances.png is skipped.", markup=False, soft_wrap=True
                )
            elif rasterize_fn is not None:
                try:
                    views = training_views(pipeline, self.num_views, self.picture_width)
                except Exception as err:  # a missing dataset must not stop the PLY export
                    CONSOLE.print(
                        f"[yellow]Training cameras unavailable ({type(err).__name__}: {err}); instances.png is skipped."
                    )
            log = lambda message: CONSOLE.print(  # noqa: E731
                message, style="bold yellow" if message.startswith("Warning") else None, soft_wrap=True, markup=False
            )
            instances = run_instances(
                scene,
                Path(self.load_config).parent,
                settings,
                pipeline=pipeline,
                rasterize_fn=rasterize_fn or default_rasterizer(),
                log=log,
                masks_unavailable=missing,
            )
            manifest = export_instances(
                scene,
                self.output_dir,
                level=self.level,
                remove=list(self.remove),
                views=views,
                rasterize_fn=rasterize_fn,
                render_device=device,
                source=str(self.load_config),
                output_flag="--output-dir",
                instances=instances,
            )
        export = manifest["export"]
        for level_name, count in export["nonfinite_votes"].items():
            if count:
                CONSOLE.print(
                    f"Warning: {count} Gaussians with vote support at level {level_name!r} have a NaN/Inf mean or vote offset "
                    "and were exported as background (the run diverged there)",
                    style="bold yellow",
                    soft_wrap=True,
                    markup=False,
                )
        chosen = next(level for level in manifest["levels"] if level["name"] == export["level"])
        CONSOLE.print(
            f"[bold green]Exported {chosen['num_instances']} instances of level {export['level']!r} "
            f"({export['ply_counts']['scene']} Gaussians) to {self.output_dir}"
        )
