"""A trained run ready for selection (paper §3.4): its Gaussians, the instances of one level, its cameras.

:class:`QueryScene` is what ``votesplat query``, ``click`` and ``query-eval`` work on (see
``ns/query.py``). The instances are the run's (``ns/run_instances.py``: the same record the export and
the viewer read), or those of an export's ``instance_ids.npz``. Instance id maps are rendered with
:func:`~votesplat_ns.core.instances.render_instance_ids` and the last few are kept.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable, Dict, List, Literal, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from votesplat_ns.core.cameras import PinholeView, scaled_view
from votesplat_ns.core.instances import InstanceSet, LevelInstances, render_instance_ids, vote_level_index
from votesplat_ns.core.ply_io import GaussianRows
from votesplat_ns.core.scene import TrainedScene
from votesplat_ns.core.semantics import click_select, isolate
from votesplat_ns.ns.rasterizer import rasterize
from votesplat_ns.ns.run import dataset_views, load_run
from votesplat_ns.ns.run_instances import InstanceSettings, run_instances

# Rendered instance id maps a QueryScene keeps (repeated clicks and feature rebuilds reuse them).
ID_MAPS_KEPT = 8


def _sha256(*arrays: np.ndarray) -> str:
    digest = hashlib.sha256()
    for array in arrays:
        array = np.ascontiguousarray(array)
        digest.update(str((array.dtype.str, array.shape)).encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


class QueryScene:
    """A trained run ready for selection: its Gaussians, the instances of one level, its cameras.

    Build it with :meth:`from_config` (loads the checkpoint through nerfstudio) or directly from
    parameters and cameras (tests, other front ends). ``params`` is the run's :class:`TrainedScene`;
    ``train_views``/``eval_views`` are lists of ``(PinholeView, image_loader)`` where
    ``image_loader()`` returns the view's image as [H, W, 3] uint8 at the camera's resolution.
    """

    def __init__(
        self,
        params: TrainedScene,
        level: LevelInstances,
        train_views: Sequence[Tuple[PinholeView, Any]],
        eval_views: Sequence[Tuple[PinholeView, Any]] = (),
        run_dir: Optional[Path] = None,
        device: Union[str, torch.device] = "cpu",
        rasterize_mode: str = "classic",
        instances_source: str = "clustered",
    ) -> None:
        self.params = params
        self.level = level
        self.train_views = list(train_views)
        self.eval_views = list(eval_views)
        self.run_dir = Path(run_dir) if run_dir is not None else None
        self.device = torch.device(device)
        self.rasterize_mode = rasterize_mode
        self.instances_source = instances_source
        n = params.num_gaussians
        if level.ids.shape != (n,):
            raise ValueError(f"instance ids cover {level.ids.shape[0]} Gaussians but the model has {n}")
        finite = params.finite(colours=True)
        self.finite = finite
        self.means, self.quats, self.scales, self.opacities, self.colors, self.sh_degree = params.gaussians(
            finite, self.device
        )[:6]
        self.ids = torch.as_tensor(level.ids[finite], dtype=torch.long, device=self.device)
        self._id_maps: "OrderedDict[tuple, np.ndarray]" = OrderedDict()

    # ------------------------------------------------------------------ loading
    @classmethod
    def from_config(
        cls,
        load_config: Path,
        level: Optional[str] = None,
        instances: Optional[Path] = None,
        settings: Optional[InstanceSettings] = None,
        log: Optional[Callable[[str], None]] = None,
        data: Optional[Path] = None,
    ) -> "QueryScene":
        """Load a run's checkpoint (``ns/run.load_run``: read safely, errors as one line) and get the instances of
        ``level``: the run's instances (:func:`~votesplat_ns.ns.run_instances.run_instances`, as the export and the
        viewer read them) or, with ``instances``, those of an export folder. ``data``: the run's dataset, which
        moved (``--data``)."""
        load_config = Path(load_config)
        pipeline, params, _ = load_run(load_config, data=data)
        model = pipeline.model
        device = torch.device(params.device)
        level_instances, source = instances_of_level(
            params,
            level,
            instances,
            lambda: run_instances(
                params, load_config.parent, settings or InstanceSettings(), pipeline, rasterize_fn=rasterize, log=log
            ),
        )
        datamanager = pipeline.datamanager
        train_views = split_views(datamanager, "train")
        eval_views = split_views(datamanager, "eval")
        rasterize_mode = getattr(getattr(model, "config", None), "rasterize_mode", "classic")
        return cls(
            params,
            level_instances,
            train_views,
            eval_views,
            run_dir=load_config.parent,
            device=device,
            rasterize_mode=rasterize_mode,
            instances_source=source,
        )

    # ------------------------------------------------------------------ cameras
    def train_camera(self, index: int, max_width: Optional[int] = None) -> PinholeView:
        if not isinstance(index, (int, np.integer)) or not 0 <= index < len(self.train_views):
            raise ValueError(
                f"view {index} is out of range: this run has {len(self.train_views)} training views "
                f"(pass --view/--views between 0 and {len(self.train_views) - 1})"
            )
        camera = self.train_views[index][0]
        return camera if max_width is None else scaled_view(camera, max_width)

    def train_image(self, index: int, camera: Optional[PinholeView] = None) -> np.ndarray:
        """The training image of view ``index`` as uint8 [H, W, 3], area-resized to ``camera``'s size."""
        full_camera = self.train_camera(index)
        image = np.asarray(self.train_views[index][1]())
        if image.shape[:2] != (full_camera.height, full_camera.width):
            raise ValueError(
                f"training image {full_camera.name} is {image.shape[1]}x{image.shape[0]} but its camera is "
                f"{full_camera.width}x{full_camera.height}; check the dataset"
            )
        if camera is not None and (camera.width, camera.height) != (full_camera.width, full_camera.height):
            resized = torch.nn.functional.interpolate(
                torch.from_numpy(image).permute(2, 0, 1)[None].float(), size=(camera.height, camera.width), mode="area"
            )[0].permute(1, 2, 0)
            image = resized.round().clamp(0, 255).to(torch.uint8).numpy()
        return image

    def camera_for_image(self, name: str) -> PinholeView:
        """The camera of the training or evaluation image whose file stem equals ``name``'s."""
        stem = Path(name).stem
        for camera, _ in self.train_views + self.eval_views:
            if Path(camera.name).stem == stem:
                return camera
        known = [Path(camera.name).name for camera, _ in self.train_views + self.eval_views]
        raise ValueError(
            f"no training or evaluation image named like {name!r} in this run (it has {len(known)} images, e.g. "
            f"{known[:3]}); the labels must belong to the run's dataset"
        )

    # ------------------------------------------------------------------ rendering
    def instance_counts(self) -> Dict[int, int]:
        return {i: int(c) for i, c in enumerate(self.level.counts)}

    def id_map(self, camera: PinholeView) -> np.ndarray:
        """Rendered instance id map [H, W] int32 (-1 = none) of ``camera`` (the last few are kept)."""
        key = (camera.width, camera.height, camera.viewmat.cpu().numpy().tobytes(), camera.K.cpu().numpy().tobytes())
        if key in self._id_maps:
            self._id_maps.move_to_end(key)
            return self._id_maps[key]
        id_map = (
            render_instance_ids(
                rasterize,
                self.means,
                self.quats,
                self.scales,
                self.opacities,
                self.ids,
                camera.viewmat.to(self.device),
                camera.K.to(self.device),
                camera.width,
                camera.height,
                rasterize_mode=self.rasterize_mode,
            )
            .to(torch.int32)
            .cpu()
            .numpy()
        )
        id_map.setflags(write=False)
        self._id_maps[key] = id_map
        while len(self._id_maps) > ID_MAPS_KEPT:
            self._id_maps.popitem(last=False)
        return id_map

    def instance_at(self, view: int, x: float, y: float) -> Optional[int]:
        """The instance under continuous pixel (x, y) of training view ``view`` (None: background)."""
        return click_select(self.id_map(self.train_camera(view)), float(x), float(y))

    @torch.no_grad()
    def render(self, keep: np.ndarray, camera: PinholeView) -> Tuple[np.ndarray, np.ndarray]:
        """RGB [H, W, 3] in [0, 1] (black background) and accumulated opacity [H, W] of the kept Gaussians."""
        kept = torch.as_tensor(np.asarray(keep, dtype=bool)[self.finite], device=self.device)
        if not bool(kept.any()):
            return np.zeros((camera.height, camera.width, 3), np.float32), np.zeros(
                (camera.height, camera.width), np.float32
            )
        colors, alphas, _ = rasterize(
            self.means[kept],
            self.quats[kept],
            self.scales[kept],
            self.opacities[kept],
            self.colors[kept],
            camera.viewmat.to(self.device)[None].float(),
            camera.K.to(self.device)[None].float(),
            int(camera.width),
            int(camera.height),
            sh_degree=self.sh_degree,
            rasterize_mode=self.rasterize_mode,
        )
        return colors[0].clamp(0, 1).cpu().numpy(), alphas[0, ..., 0].cpu().numpy()

    def selection_mask(self, selected: Sequence[int]) -> np.ndarray:
        """[N] bool over all Gaussians of the model: members of the selected instances."""
        return np.asarray(isolate(self.level.ids, list(selected)), dtype=bool)

    def vertex_rows(self) -> GaussianRows:
        """The PLY vertex rows of every Gaussian, made per chunk as a file is written (``ply_io.GaussianRows``)."""
        return self.params.vertex_rows()

    def fingerprint(self) -> Dict[str, Any]:
        """What the instance features of this scene depend on, besides encoder and views."""
        p = self.params
        return {
            "gaussians_sha256": _sha256(
                p.means.astype(np.float32),
                p.opacity_logits.astype(np.float32),
                p.log_scales.astype(np.float32),
                p.quats.astype(np.float32),
            ),
            "instance_ids_sha256": _sha256(self.level.ids.astype(np.int64)),
            "level": self.level.name,
            "num_gaussians": int(p.means.shape[0]),
        }


def instances_of_level(
    params, level: Optional[str], instances_dir: Optional[Path], run_instances_fn: Callable[[], InstanceSet]
) -> Tuple[LevelInstances, str]:
    """The instances of one vote level: read from an export folder, or the run's (``run_instances_fn()``)."""
    names = params.level_names
    n = params.means.shape[0]
    if instances_dir is not None:
        instance_set = InstanceSet.load(instances_dir)
        if instance_set.num_gaussians != n:
            raise ValueError(
                f"the export in {instances_dir} has {instance_set.num_gaussians} Gaussians but this run's checkpoint "
                f"has {n}; export again from this checkpoint or drop --instances"
            )
        chosen = instance_set.level(level)
        source = f"export {instances_dir}"
    else:
        index = vote_level_index(names, level)
        chosen = run_instances_fn().levels[index]
        source = "run"
    if chosen.num_instances == 0:
        raise ValueError(
            f"vote level {chosen.name!r} has no instances (no foreground Gaussians, or all votes were noise); "
            "check that the run trained with the vote loss, or lower --min-cluster-size"
        )
    return chosen, source


def split_views(datamanager, split: Literal["train", "eval"]) -> List[Tuple[PinholeView, Any]]:
    """Cameras and lazy uint8 image loaders of a nerfstudio full-image datamanager's split.

    Images of distorted cameras are taken from nerfstudio's undistorted cache, whose loading also
    rewrites the cameras' intrinsics, so image and camera always agree.
    """
    dataset = datamanager.train_dataset if split == "train" else datamanager.eval_dataset
    if dataset is None:
        return []
    cameras = dataset.cameras
    distorted = cameras.distortion_params is not None and bool((cameras.distortion_params != 0).any())
    if distorted:
        cache = datamanager.cached_train if split == "train" else datamanager.cached_eval
        cameras = dataset.cameras

        def loader(index: int):
            return lambda: _uint8_image(cache[index]["image"])
    else:

        def loader(index: int):
            return lambda: _uint8_image(dataset.get_data(index, image_type="uint8")["image"])

    views = dataset_views(dataset, cameras=cameras)
    return [(view, loader(index)) for index, view in enumerate(views)]


def _uint8_image(image) -> np.ndarray:
    image = image.detach().cpu() if torch.is_tensor(image) else torch.as_tensor(np.asarray(image))
    image = image[..., :3]
    if image.dtype != torch.uint8:
        image = (image.float().clamp(0, 1) * 255).round().to(torch.uint8)
    return image.numpy()


def evenly_spaced(count: int, limit: Optional[int]) -> List[int]:
    """Up to ``limit`` indices spread evenly over range(count) (all when limit is None or 0)."""
    if not limit or limit >= count:
        return list(range(count))
    return sorted({int(round(x)) for x in np.linspace(0, count - 1, limit)})
