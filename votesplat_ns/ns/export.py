"""Export VoteSplat instances: ``ns-export votesplat-instances`` / ``votesplat-export`` (paper §3.4).

Output folder (every PLY is a standard 3DGS file, see ``ply_io``):

    instances.json            manifest: levels, per instance count/bbox/vote centre/parent/file,
                              clustering parameters, written files
    instance_ids.npz          per-Gaussian instance ids of every level (before PLY filtering)
    scene.ply                 the whole scene
    scene_instance_ids.npy    int32 instance id (export level) of each scene.ply vertex, -1 = none
    background.ply            Gaussians in no instance at the export level (background and noise)
    instances/instance_XXXX.ply   one file per instance of the export level
    scene_without_<ids>.ply   the scene minus the instances asked for with ``remove`` (object removal)
    instances.png             instance colours from a few training views (if a renderer is available)

The folder is built next to the target and renamed into place at the end, so an interrupted
export leaves nothing half-written. An existing target is replaced only if it is empty or holds a
previous export (an instances.json) and nothing else: a file the export does not write (a user's
notes, say) makes the export stop before any work, naming the file, rather than delete it. Every
folder of a previous export must be writable, so that it can be deleted once replaced.

This module keeps nerfstudio imports inside functions: the plugin's method entry point imports it
(for ``install_ns_export_hook``) while nerfstudio is still importing its method configs.
"""

from __future__ import annotations

import contextlib
import fnmatch
import importlib.abc
import os
import shutil
import sys
import types
import typing
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, Iterator, List, Literal, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import torch
import tyro
from typing_extensions import Annotated

from votesplat_ns.cli.cli_errors import VoteSplatInputError, check_writable_folder, one_line_errors, writing_into
from votesplat_ns.core.cameras import PinholeView
from votesplat_ns.core.clustering import DEFAULT_MAX_POINTS, cluster_levels
from votesplat_ns.core.instances import (
    IDS_NAME,
    MANIFEST_NAME,
    InstanceSet,
    render_instance_ids,
    save_instance_picture,
    vote_level_index,
)
from votesplat_ns.core.ply_io import make_temp_dir, temp_sibling, write_gaussian_table, write_instance_id_file
from votesplat_ns.core.scene import VOTE_OFFSETS_KEY, VOTE_SUPPORT_KEY, TrainedScene  # noqa: F401 (keys re-exported)
from votesplat_ns.ns.mask_views import DEFAULT_MASK_VIEWS, mask_check
from votesplat_ns.ns.run import camera_view, evenly_spaced, load_run

SUBCOMMAND_NAME = "votesplat-instances"
EXPORTER_MODULE = "nerfstudio.scripts.exporter"


def _scene_of(model_or_params, level_names: Optional[Sequence[str]], sh_degree: Optional[int]) -> TrainedScene:
    """The :class:`TrainedScene` of a model, a gauss_params-like mapping, or the scene itself."""
    if isinstance(model_or_params, TrainedScene):
        return model_or_params
    if hasattr(model_or_params, "gauss_params"):
        return TrainedScene.from_model(model_or_params, level_names, sh_degree)
    if isinstance(model_or_params, Mapping):
        return TrainedScene.from_params(model_or_params, level_names, sh_degree)
    raise ValueError(
        f"expected a VoteSplat model or a dict of Gaussian parameters, got {type(model_or_params).__name__}"
    )


@contextlib.contextmanager
def _progress(enabled: bool) -> Iterator[Callable[..., Callable[[int], None]]]:
    """``task(description, total) -> advance(n)``; a rich progress bar when enabled."""
    if not enabled:
        yield lambda description, total=None: lambda n=1: None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), transient=False
    ) as bar:

        def task(description: str, total: Optional[int] = None) -> Callable[[int], None]:
            task_id = bar.add_task(description, total=total)
            return lambda n=1: bar.advance(task_id, n)

        yield task


# Everything an export writes (paths relative to its folder); anything else in a previous export is the user's.
EXPORT_FILE_PATTERNS = (
    MANIFEST_NAME,
    IDS_NAME,
    "scene.ply",
    "scene_instance_ids.npy",
    "background.ply",
    "instances.png",
    "scene_without_*.ply",
    "instances/instance_*.ply",
)


def _foreign_entries(folder: Path) -> List[str]:
    """Paths (relative, sorted) inside a previous export that no export writes, e.g. a user's notes."""
    foreign = []
    for root, dirs, files in os.walk(folder):
        for name in dirs + files:
            path = Path(root) / name
            relative = path.relative_to(folder).as_posix()
            if relative == "instances" and path.is_dir() and not path.is_symlink():
                continue
            is_file = path.is_file() and not path.is_symlink()
            if not (is_file and any(fnmatch.fnmatchcase(relative, pattern) for pattern in EXPORT_FILE_PATTERNS)):
                foreign.append(relative)
    return sorted(foreign)


def _check_output_dir(output_dir: Path, flag: str = "output_dir") -> None:
    """Fail before any work if ``output_dir`` cannot be (re)placed: see the module docstring."""
    if output_dir.exists() and not output_dir.is_dir():
        raise VoteSplatInputError(f"{flag} {output_dir} is a file; pass a folder path (it is created if missing)")
    if output_dir.is_dir() and any(output_dir.iterdir()):
        if not (output_dir / MANIFEST_NAME).is_file():
            raise VoteSplatInputError(
                f"{flag} {output_dir} is a non-empty folder that is not a previous instance export; "
                "choose a new or empty folder (it would be replaced)"
            )
        foreign = _foreign_entries(output_dir)
        if foreign:
            more = f" (and {len(foreign) - 1} more)" if len(foreign) > 1 else ""
            raise VoteSplatInputError(
                f"{flag} {output_dir} holds {foreign[0]}{more}, which an instance export does not write; replacing the "
                f"previous export would delete it: move it out of that folder, or choose another {flag}"
            )
        for folder in (output_dir, output_dir / "instances"):
            if folder.is_dir() and not os.access(folder, os.W_OK | os.X_OK):
                raise VoteSplatInputError(
                    f"{flag} {output_dir}: the previous export's folder {folder} is not writable, so it could not be deleted "
                    f"once replaced; make it writable, or choose another {flag}"
                )
    # the new export is built beside the target
    check_writable_folder(output_dir.parent, flag, given=output_dir)


def _nonfinite_votes(params: TrainedScene) -> Dict[str, int]:
    """Per level: supervised Gaussians (support > 0) whose mean or vote offset is NaN/Inf (clustering treats them as background)."""
    finite_means = np.isfinite(params.means).all(axis=1)
    counts = {}
    for index, name in enumerate(params.level_names):
        support = params.vote_support[:, index]
        supervised = np.isfinite(support) & (support > 0)
        counts[name] = int(
            (supervised & ~(finite_means & np.isfinite(params.vote_offsets[:, index]).all(axis=1))).sum()
        )
    return counts


def _move_into_place(staging: Path, output_dir: Path) -> None:
    if output_dir.exists():
        old = temp_sibling(output_dir, ".old")
        output_dir.rename(old)
        try:
            staging.rename(output_dir)
        except BaseException:
            old.rename(output_dir)
            raise
        try:
            shutil.rmtree(old)
        except OSError as error:  # checked beforehand (_check_output_dir); say so rather than hide it
            warnings.warn(f"the previous export was replaced but could not be deleted ({error}); delete {old} yourself")
    else:
        staging.rename(output_dir)


def export_instances(
    model_or_params,
    output_dir: Union[str, Path],
    level: Union[int, str, None] = None,
    remove: Optional[Sequence[int]] = None,
    views: Optional[Sequence[PinholeView]] = None,
    rasterize_fn: Optional[Callable[..., tuple]] = None,
    level_names: Optional[Sequence[str]] = None,
    sh_degree: Optional[int] = None,
    min_cluster_size: Optional[int] = None,
    min_samples: Optional[int] = None,
    max_points: int = DEFAULT_MAX_POINTS,
    noise: Literal["nearest", "drop"] = "nearest",
    noise_radius: Optional[float] = None,
    cluster_selection_epsilon: float = 0.0,
    seed: int = 0,
    coarse_to_fine: bool = True,
    render_device: Union[str, torch.device, None] = None,
    progress: bool = True,
    source: Optional[str] = None,
    output_flag: str = "output_dir",
    refine: Optional[Callable[[int, str, np.ndarray], tuple]] = None,
) -> Dict[str, object]:
    """Cluster the votes of every level and write the export folder described in the module doc.

    model_or_params: a VoteSplat model (reads ``gauss_params``, ``config.vote_levels`` and
    ``config.sh_degree``) or a mapping with splatfacto's raw gauss_params plus ``vote_offsets``
    [N, L, 3] and ``vote_support`` [N, L]. ``level`` (name or index, default the first level)
    selects whose instances get their own PLY; ``remove`` lists instance ids of that level to cut
    out of the scene. ``views`` and ``rasterize_fn`` (gsplat ``rasterization`` signature) draw
    instances.png. ``output_flag`` names ``output_dir`` in error messages (the CLI's --output-dir).
    ``refine`` is passed to :func:`cluster_levels` (the training-mask check).
    Returns the manifest written to instances.json; its ``export.nonfinite_votes`` counts, per
    level, the supervised Gaussians whose vote is NaN/Inf and so became background.
    """
    output_dir = Path(output_dir)
    _check_output_dir(output_dir, output_flag)
    params = _scene_of(model_or_params, level_names, sh_degree)
    n = params.means.shape[0]
    if n == 0:
        raise ValueError("the model has no Gaussians to export")
    names = params.level_names
    level_index = vote_level_index(names, level)
    level_name = names[level_index]

    foreground_count = int(
        ((params.vote_support[:, level_index] > 0) & np.isfinite(params.vote_support[:, level_index])).sum()
    )
    if foreground_count == 0:
        raise ValueError(
            f"no foreground Gaussians at vote level {level_name!r}: vote_support is zero everywhere "
            "(the model never received vote supervision; check the masks and that training ran with the vote loss)"
        )

    with _progress(progress) as task:
        advance = task("clustering votes", total=len(names))
        instance_set = cluster_levels(
            params.means,
            params.vote_offsets,
            params.vote_support,
            names,
            min_cluster_size=min_cluster_size,
            min_samples=min_samples,
            max_points=max_points,
            seed=seed,
            noise=noise,
            noise_radius=noise_radius,
            coarse_to_fine=coarse_to_fine,
            cluster_selection_epsilon=cluster_selection_epsilon,
            on_level=lambda index, name: advance(1) if index > 0 else None,
            refine=refine,
        )
        advance(1)
        instance_set.validate()
        chosen = instance_set.levels[level_index]
        if not chosen.foreground.any():
            raise ValueError(
                f"no foreground Gaussians with finite votes at vote level {level_name!r}: every supervised Gaussian "
                "has a NaN/Inf mean or vote offset (the checkpoint diverged)"
            )
        if chosen.num_instances == 0:
            used = chosen.clustering
            raise ValueError(
                f"every one of the {int(chosen.foreground.sum())} foreground votes at level {level_name!r} was labelled noise "
                f"(min_cluster_size={used.get('min_cluster_size')}, min_samples={used.get('min_samples')}); "
                "lower --min-cluster-size / --min-samples or use --noise nearest"
            )
        remove_ids = sorted({int(i) for i in (remove or [])})
        bad = [i for i in remove_ids if not 0 <= i < chosen.num_instances]
        if bad:
            raise ValueError(
                f"cannot remove instances {bad}: level {level_name!r} has instances 0..{chosen.num_instances - 1}"
            )

        output_dir.parent.mkdir(parents=True, exist_ok=True)
        staging = make_temp_dir(output_dir, ".partial")  # umask permissions: it becomes the export folder
        try:
            manifest = _write_export(
                params,
                instance_set,
                level_index,
                remove_ids,
                staging,
                views,
                rasterize_fn,
                render_device,
                task,
                source,
                _nonfinite_votes(params),
            )
            _move_into_place(staging, output_dir)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
    return manifest


def _write_export(
    params: TrainedScene,
    instance_set: InstanceSet,
    level_index: int,
    remove_ids: List[int],
    folder: Path,
    views: Optional[Sequence[PinholeView]],
    rasterize_fn,
    render_device,
    task,
    source: Optional[str],
    nonfinite_votes: Dict[str, int],
) -> Dict[str, object]:
    chosen = instance_set.levels[level_index]
    ids = chosen.ids
    table = params.vertex_table()
    width = max(4, len(str(chosen.num_instances - 1)))
    (folder / "instances").mkdir()
    advance = task("writing PLY files", total=chosen.num_instances + 2 + bool(remove_ids))

    written = write_gaussian_table(folder / "scene.ply", table)
    write_instance_id_file(folder / "scene_instance_ids.npy", ids[written])
    advance(1)
    files: Dict[str, object] = {"scene": "scene.ply", "scene_instance_ids": "scene_instance_ids.npy"}
    counts: Dict[str, int] = {"scene": int(written.size)}

    background = write_gaussian_table(folder / "background.ply", table, select=ids < 0)
    files["background"] = "background.ply"
    counts["background"] = int(background.size)
    advance(1)

    per_instance: Dict[int, Dict[str, object]] = {}
    for instance_id, members in chosen.members().items():
        name = f"instances/instance_{instance_id:0{width}d}.ply"
        kept = write_gaussian_table(folder / name, table, select=members)
        per_instance[instance_id] = {"file": name, "ply_count": int(kept.size)}
        advance(1)

    removal = None
    if remove_ids:
        name = "scene_without_" + "_".join(str(i) for i in remove_ids) + ".ply"
        kept = write_gaussian_table(folder / name, table, select=~np.isin(ids, remove_ids))
        removal = {"ids": remove_ids, "file": name, "ply_count": int(kept.size)}
        advance(1)

    picture = None
    if views and rasterize_fn is not None:
        picture = _write_picture(params, ids, views, rasterize_fn, render_device, folder / "instances.png", task)

    extra = {
        "export": {
            "level": chosen.name,
            "level_index": level_index,
            "files": files,
            "ply_counts": counts,
            "removed": removal,
            "picture": picture,
            "source": source,
            "nonfinite_votes": nonfinite_votes,
            "ply_filter": "vertices with NaN/Inf or opacity logit < -5.5373 are not written (as ns-export gaussian-splat)",
        }
    }
    return instance_set.save(folder, instance_extra={chosen.name: per_instance}, extra=extra)


def _write_picture(
    params: TrainedScene, ids: np.ndarray, views: Sequence[PinholeView], rasterize_fn, device, path: Path, task
) -> str:
    device = torch.device(device) if device is not None else torch.device("cpu")
    finite = params.finite()
    means, quats, scales, opacities, _, _ = params.gaussians(finite, device)
    instance_ids = torch.as_tensor(ids[finite], device=device)
    advance = task("rendering instance views", total=len(views))
    maps, images = [], []
    for view in views:
        id_map = render_instance_ids(
            rasterize_fn,
            means,
            quats,
            scales,
            opacities,
            instance_ids,
            view.viewmat.to(device),
            view.K.to(device),
            int(view.width),
            int(view.height),
        )
        maps.append(id_map.cpu().numpy())
        images.append(view.image)
        advance(1)
    have_images = all(image is not None for image in images)
    save_instance_picture(path, maps, images if have_images else None)
    return path.name


# ----------------------------------------------------------------------------- nerfstudio glue


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

    def main(self) -> None:
        from nerfstudio.utils.rich_utils import CONSOLE

        # bad input (ValueError, VoteSplatInputError) ends the command with one line, exit 1
        with one_line_errors(catch=(ValueError,)), writing_into(self.output_dir, "--output-dir"):
            _check_output_dir(self.output_dir, "--output-dir")  # before the checkpoint is loaded
            pipeline, scene, _ = load_run(self.load_config)
            device = torch.device(scene.device)
            views: List[PinholeView] = []
            rasterize_fn = default_rasterizer() if self.num_views > 0 else None
            if rasterize_fn is None and self.num_views > 0:
                CONSOLE.print("[yellow]No rasterizer available on this device; instances.png is skipped.")
            elif rasterize_fn is not None:
                try:
                    views = training_views(pipeline, self.num_views, self.picture_width)
                except Exception as err:  # a missing dataset must not stop the PLY export
                    CONSOLE.print(
                        f"[yellow]Training cameras unavailable ({type(err).__name__}: {err}); instances.png is skipped."
                    )
            refine = None
            if self.mask_check:
                check_rasterizer = rasterize_fn or default_rasterizer()
                if check_rasterizer is None:
                    raise ValueError(
                        "--mask-check needs a rasterizer (gsplat or the torch fallback); pass --mask-check False"
                    )
                try:
                    refine = mask_check(pipeline, scene, check_rasterizer, max_views=self.mask_check_views)
                except (OSError, ValueError) as err:  # the instances are still valid without it
                    CONSOLE.print(
                        f"Warning: the training masks are unavailable ({err}); exporting the vote clustering without the mask "
                        "check (--mask-check False does this on purpose)",
                        style="bold yellow",
                        soft_wrap=True,
                        markup=False,
                    )
            manifest = export_instances(
                scene,
                self.output_dir,
                level=self.level,
                remove=list(self.remove),
                views=views,
                rasterize_fn=rasterize_fn,
                min_cluster_size=self.min_cluster_size,
                min_samples=self.min_samples,
                max_points=self.max_points,
                noise=self.noise,
                noise_radius=self.noise_radius,
                cluster_selection_epsilon=self.cluster_selection_epsilon,
                seed=self.seed,
                render_device=device,
                source=str(self.load_config),
                output_flag="--output-dir",
                refine=refine,
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


def entrypoint() -> None:
    """Console script ``votesplat-export``, an alias of ``votesplat export`` (lazy import: cli.main imports this module)."""
    from votesplat_ns.cli.main import alias

    alias("export", "votesplat-export")


# ----------------------------------------------------------------------------- ns-export hook


def _extend_commands(exporter) -> bool:
    """Rebind exporter.Commands to nerfstudio's union plus our subcommand. False if not defined yet."""
    commands = exporter.__dict__.get("Commands")
    if commands is None:
        return False
    if getattr(exporter, "_votesplat_instances_hooked", False):
        return True
    markers: tuple = ()
    inner = commands
    if typing.get_origin(commands) is Annotated:
        inner, *rest = typing.get_args(commands)
        markers = tuple(rest)
    members = typing.get_args(inner) if typing.get_origin(inner) is Union else (inner,)
    ours = Annotated[ExportVoteSplatInstances, tyro.conf.subcommand(name=SUBCOMMAND_NAME)]
    extended = Union[tuple(members) + (ours,)]  # type: ignore[valid-type]
    exporter.Commands = Annotated[(extended, *markers)] if markers else extended
    exporter._votesplat_instances_hooked = True
    return True


class _ExporterBeingImported(types.ModuleType):
    """Module class swapped onto a half-imported exporter: extends Commands on first outside use.

    When the hook runs during nerfstudio's method discovery, ns-export is still executing
    exporter.py (Commands is defined further down). Module-level assignments go straight to the
    module dict, so we wait for the first attribute read from outside (the console script's
    ``from nerfstudio.scripts.exporter import entrypoint``), which happens after the import ends.
    """

    def __getattribute__(self, name: str):
        namespace = types.ModuleType.__getattribute__(self, "__dict__")
        if not name.startswith("__") and "Commands" in namespace:
            object.__setattr__(self, "__class__", types.ModuleType)
            _extend_commands(self)
        return types.ModuleType.__getattribute__(self, name)


class _PatchingLoader(importlib.abc.Loader):
    def __init__(self, inner):
        self._inner = inner

    def create_module(self, spec):
        return self._inner.create_module(spec)

    def exec_module(self, module) -> None:
        self._inner.exec_module(module)
        _extend_commands(module)

    def __getattr__(self, name: str):
        return getattr(self._inner, name)


class _ExporterFinder(importlib.abc.MetaPathFinder):
    """Wraps the loader of the exporter module so Commands is extended right after it executes."""

    def __init__(self, module_name: str):
        self.module_name = module_name

    def find_spec(self, fullname, path, target=None):
        if fullname != self.module_name:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None and spec.loader is not None:
                spec.loader = _PatchingLoader(spec.loader)
                return spec
        return None


def install_ns_export_hook(module_name: str = EXPORTER_MODULE) -> None:
    """Make ``ns-export votesplat-instances`` available (nerfstudio 1.1.5 has no exporter plugins).

    Cheap and idempotent; call it from the plugin's method entry point module. ns-export imports
    nerfstudio.scripts.exporter, whose import of eval_utils -> method_configs discovers (imports)
    every method entry point *before* exporter.py defines Commands, so three cases are handled:
    exporter fully imported (extend now), half imported (extend on its first use from outside,
    see ``_ExporterBeingImported``), not imported yet (a meta-path finder extends it right after
    it executes; nothing heavy is imported here, so ns-train does not pay for open3d).
    ``module_name`` exists for tests.
    """
    exporter = sys.modules.get(module_name)
    if exporter is not None:
        if not _extend_commands(exporter) and type(exporter) is types.ModuleType:
            exporter.__class__ = _ExporterBeingImported
        return
    if not any(isinstance(f, _ExporterFinder) and f.module_name == module_name for f in sys.meta_path):
        sys.meta_path.insert(0, _ExporterFinder(module_name))
