"""Write VoteSplat instances to a folder (paper §3.4): :func:`export_instances`, used by ``ns-export
votesplat-instances`` / ``votesplat export`` (``ns/export.py``) and by benchmarks.

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

No nerfstudio import: it works on a :class:`~votesplat_ns.core.scene.TrainedScene`, a model, or a
mapping of Gaussian parameters.
"""

from __future__ import annotations

import contextlib
import fnmatch
import os
import shutil
import warnings
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Mapping, Optional, Sequence, Union

import numpy as np
import torch

from votesplat_ns.core.cameras import PinholeView
from votesplat_ns.core.clustering import ClusteringOptions, cluster_levels
from votesplat_ns.core.instances import (
    IDS_NAME,
    MANIFEST_NAME,
    InstanceSet,
    render_id_maps,
    save_instance_picture,
    vote_level_index,
)
from votesplat_ns.core.ply_io import (
    make_temp_dir,
    sweep_leftovers,
    temp_sibling,
    write_gaussian_table,
    write_instance_id_file,
)
from votesplat_ns.core.scene import TrainedScene
from votesplat_ns.errors import VoteSplatInputError, check_writable_folder


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


def check_output_dir(output_dir: Path, flag: str = "output_dir") -> None:
    """Fail before any work if ``output_dir`` cannot be (re)placed: see the module docstring.

    The folder the command runs in (``--output-dir .`` inside a previous export), or one that holds it, is
    refused too: it cannot be renamed away while a process works in it, and the shell would be left in a
    deleted folder.
    """
    here = Path.cwd().resolve()
    if output_dir.resolve() == here or output_dir.resolve() in here.parents:
        raise VoteSplatInputError(
            f"{flag} {output_dir} is the folder this command runs in ({here}){' or holds it' if output_dir.resolve() != here else ''}, "
            f"which the export would replace; run the command from another folder (e.g. cd ..) or choose another {flag}"
        )
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
        except OSError as error:  # checked beforehand (check_output_dir); say so rather than hide it
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
    clustering: ClusteringOptions = ClusteringOptions(),
    render_device: Union[str, torch.device, None] = None,
    progress: bool = True,
    source: Optional[str] = None,
    output_flag: str = "output_dir",
    refine: Optional[Callable[[int, str, np.ndarray], tuple]] = None,
    instances: Optional[InstanceSet] = None,
) -> Dict[str, Any]:
    """Cluster the votes of every level and write the export folder described in the module doc.

    model_or_params: a VoteSplat model (reads ``gauss_params``, ``config.vote_levels`` and
    ``config.sh_degree``) or a mapping with splatfacto's raw gauss_params plus ``vote_offsets``
    [N, L, 3] and ``vote_support`` [N, L]. ``level`` (name or index, default the first level)
    selects whose instances get their own PLY; ``remove`` lists instance ids of that level to cut
    out of the scene. ``views`` and ``rasterize_fn`` (gsplat ``rasterization`` signature) draw
    instances.png. ``output_flag`` names ``output_dir`` in error messages (the CLI's --output-dir).
    ``clustering`` (HDBSCAN settings) and ``refine`` (the training-mask check) are passed to :func:`cluster_levels`;
    ``instances`` (a run's instances, :func:`votesplat_ns.ns.run_instances.run_instances`) are written as they are
    instead.
    Returns the manifest written to instances.json; its ``export.nonfinite_votes`` counts, per
    level, the supervised Gaussians whose vote is NaN/Inf and so became background.
    """
    output_dir = Path(output_dir)
    check_output_dir(output_dir, output_flag)
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
        if instances is None:
            advance = task("clustering votes", total=len(names))
            instance_set = cluster_levels(
                params.means,
                params.vote_offsets,
                params.vote_support,
                names,
                **clustering.kwargs(),
                on_level=lambda index, name: advance(1) if index > 0 else None,
                refine=refine,
            )
            advance(1)
        else:
            instance_set = instances
            if instance_set.num_gaussians != n or instance_set.level_names != tuple(names):
                raise ValueError(
                    f"the instances given cover {instance_set.num_gaussians} Gaussians of levels "
                    f"{list(instance_set.level_names)}, the scene has {n} of {list(names)}"
                )
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
        sweep_leftovers(output_dir)  # what exports killed mid-write left beside it
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
) -> Dict[str, Any]:
    chosen = instance_set.levels[level_index]
    ids = chosen.ids
    table = params.vertex_rows()  # rows made per chunk of each file: no copy of the whole table
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
    advance = task("rendering instance views", total=len(views))
    maps = render_id_maps(params, ids, views, rasterize_fn, device=device, on_view=lambda: advance(1))
    images = [view.image for view in views]
    have_images = all(image is not None for image in images)
    save_instance_picture(path, maps, images if have_images else None)
    return path.name
