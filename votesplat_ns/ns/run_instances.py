"""A trained run's instances, computed once and kept beside the run: :func:`run_instances`.

Every front end reads the instances of a run through this one function: ``ns-export
votesplat-instances`` / ``votesplat export``, ``votesplat eval``, ``votesplat query`` / ``click`` /
``query-eval`` and the ns-viewer panel (overlay, click, isolate, text query, export-selected). So
each of them shows the same ids, colours and count for the same checkpoint and settings.

The instances are the vote clustering (:func:`votesplat_ns.core.clustering.cluster_levels`) checked
against the training masks (:func:`votesplat_ns.ns.mask_views.mask_check`), for every vote level.
They are kept in ``<run>/votesplat_instances/`` (``instances.json`` and ``instance_ids.npz``, as
:meth:`~votesplat_ns.core.instances.InstanceSet.save` writes them) under a key made of:

* the Gaussians and votes of the checkpoint (a digest of their arrays, so a live viewer model and its
  saved checkpoint key alike);
* the settings (:class:`InstanceSettings`);
* the training views and masks the check reads (the run's datamanager settings: data, mask source,
  levels, downscale);
* the code that computes instances (a digest of its modules' source: their defaults live there).

A record with another key is computed again, with one line saying which part changed. A record that
cannot be written (a read-only run folder) is computed in memory, with one warning. The record is
written into a hidden sibling folder and renamed into place, so an interrupted write leaves nothing
that is later read; such leftovers are swept at the next write. When the mask check cannot run (the
dataset moved, no rasterizer), the vote clustering alone is used and nothing is kept, so that a later
call that can run the check does not read the unchecked instances.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import hashlib
import importlib
import json
import os
import re
import shutil
from pathlib import Path
from typing import Any, Callable, Dict, Mapping, Optional, Tuple

import numpy as np

from votesplat_ns.core.clustering import ClusteringOptions, cluster_levels
from votesplat_ns.core.instances import MANIFEST_NAME, InstanceSet
from votesplat_ns.core.ply_io import jsonable, make_temp_dir, replace_folder, sweep_leftovers
from votesplat_ns.core.scene import TrainedScene
from votesplat_ns.errors import VoteSplatInputError
from votesplat_ns.ns.mask_views import DEFAULT_MASK_VIEWS, mask_check

RECORD_FOLDER = "votesplat_instances"
RECORD_FORMAT = "votesplat-run-instances"
RECORD_VERSION = 1
# The modules whose code decides the instances of a run: a change in any of them (a default, a rule)
# makes a kept record stale.
INSTANCE_CODE_MODULES = (
    "votesplat_ns.core.clustering",
    "votesplat_ns.core.mask_consensus",
    "votesplat_ns.core.mask_sightings",
    "votesplat_ns.core.whole_objects",
    "votesplat_ns.core.instances",
    "votesplat_ns.ns.mask_views",
    "votesplat_ns.ns.run_instances",
)
# The parts of a key, in the order a changed one is named.
KEY_PARTS = ("gaussians", "settings", "masks", "code")
_WHAT_CHANGED = {
    "gaussians": "another checkpoint",
    "settings": "other clustering settings",
    "masks": "other training views or masks",
    "code": "another version of the instance code",
}

Log = Callable[[str], None]


@dataclasses.dataclass(frozen=True)
class InstanceSettings:
    """What a run's instances depend on besides its checkpoint: the command's settings.

    ``clustering`` are the HDBSCAN settings of the commands (``--min-cluster-size`` ...);
    ``mask_check`` / ``mask_check_views`` the training-mask check; ``mask_check_options`` further
    keywords of :func:`votesplat_ns.core.mask_consensus.regroup_with_masks` and ``cluster_options``
    of :func:`~votesplat_ns.core.clustering.cluster_levels` (benchmark variants), as sorted pairs.
    """

    clustering: ClusteringOptions = ClusteringOptions()
    mask_check: bool = True
    mask_check_views: int = DEFAULT_MASK_VIEWS
    mask_check_options: Tuple[Tuple[str, Any], ...] = ()
    cluster_options: Tuple[Tuple[str, Any], ...] = ()

    @classmethod
    def make(
        cls,
        clustering: Optional[ClusteringOptions] = None,
        mask_check: bool = True,
        mask_check_views: int = DEFAULT_MASK_VIEWS,
        mask_check_options: Optional[Mapping[str, Any]] = None,
        cluster_options: Optional[Mapping[str, Any]] = None,
    ) -> "InstanceSettings":
        """The settings of a command's flags; a mask check through no view is refused (it would check nothing)."""
        if mask_check and int(mask_check_views) < 1:
            raise VoteSplatInputError(
                f"--mask-check-views {mask_check_views}: the mask check needs 1 or more training views "
                f"(default {DEFAULT_MASK_VIEWS}); give a positive number, or --mask-check False to skip the check"
            )
        return cls(
            clustering or ClusteringOptions(),
            bool(mask_check),
            int(mask_check_views),
            tuple(sorted((mask_check_options or {}).items())),
            tuple(sorted((cluster_options or {}).items())),
        )

    def to_dict(self) -> Dict[str, Any]:
        return jsonable(
            {
                "clustering": dataclasses.asdict(self.clustering),
                "mask_check": self.mask_check,
                "mask_check_views": self.mask_check_views if self.mask_check else None,
                "mask_check_options": dict(self.mask_check_options) if self.mask_check else {},
                "cluster_options": dict(self.cluster_options),
            }
        )


def _digest(*parts: Any) -> str:
    digest = hashlib.sha256()
    for part in parts:
        if isinstance(part, np.ndarray):
            array = np.ascontiguousarray(part)
            digest.update(str((array.dtype.str, array.shape)).encode())
            digest.update(array.tobytes())
        else:
            digest.update(json.dumps(part, sort_keys=True).encode())
    return digest.hexdigest()


def gaussians_digest(scene: TrainedScene) -> str:
    """Digest of what the instances read of a scene: geometry (the mask check renders it) and votes."""
    return _digest(
        np.asarray(scene.means, np.float32),
        np.asarray(scene.log_scales, np.float32),
        np.asarray(scene.quats, np.float32),
        np.asarray(scene.opacity_logits, np.float32),
        np.asarray(scene.vote_offsets, np.float32),
        np.asarray(scene.vote_support, np.float32),
        list(scene.level_names),
    )


def code_digest() -> str:
    """Digest of the source of :data:`INSTANCE_CODE_MODULES`."""
    sources = []
    for name in INSTANCE_CODE_MODULES:
        module = importlib.import_module(name)
        sources.append(Path(module.__file__ or "").read_text(encoding="utf-8") if module.__file__ else name)
    return _digest(sources)


def masks_fingerprint(pipeline: Any) -> Optional[str]:
    """The run's datamanager settings (data, mask source, levels, downscale, ...) as text; None without one.

    The data path is made absolute and the cache folder left out, so that a command run from another folder
    (``ns/run_config.py`` ``anchor_to_run_folder``) keys alike. Function reprs carry memory addresses, which
    differ between processes; they are cut out.
    """
    config = getattr(getattr(pipeline, "datamanager", None), "config", None)
    if config is None:
        return None
    config = copy.copy(config)
    if getattr(config, "data", None) is not None:
        config.data = Path(os.path.abspath(config.data))
    if hasattr(config, "cache_dir"):
        config.cache_dir = None  # where the masks are cached does not change them
    return re.sub(r" at 0x[0-9a-fA-F]+", "", repr(config))


def record_key(scene: TrainedScene, settings: InstanceSettings, pipeline: Any) -> Dict[str, str]:
    """The key of a run's instances (see the module doc), one digest per part."""
    return {
        "gaussians": gaussians_digest(scene),
        "settings": _digest(settings.to_dict()),
        "masks": _digest(masks_fingerprint(pipeline) if settings.mask_check else None),
        "code": code_digest(),
    }


def _read_record(folder: Path) -> Optional[Tuple[Dict[str, str], Path]]:
    """The key of the record in ``folder`` (None: no readable record there)."""
    manifest = folder / MANIFEST_NAME
    try:
        record = json.loads(manifest.read_text(encoding="utf-8")).get("record", {})
    except (OSError, ValueError, AttributeError):
        return None
    if not isinstance(record, dict) or record.get("format") != RECORD_FORMAT or not isinstance(record.get("key"), dict):
        return None
    return record["key"], folder


def compute_instances(
    scene: TrainedScene,
    settings: InstanceSettings,
    pipeline: Any = None,
    rasterize_fn: Optional[Callable[..., tuple]] = None,
    on_level: Optional[Callable[[int, str], None]] = None,
    log: Optional[Log] = None,
    masks_unavailable: Optional[str] = None,
) -> Tuple[InstanceSet, bool]:
    """The instances of every level of ``scene``; returns them and whether the mask check ran.

    Without a ``pipeline`` whose datamanager has the training masks, or without ``rasterize_fn``, the
    check cannot run: ``log`` says so once (with ``masks_unavailable``, the caller's reason) and the vote
    clustering alone is returned.
    """
    refine = None
    if settings.mask_check:
        reason = None
        if pipeline is None or rasterize_fn is None:
            reason = masks_unavailable or "no training views or rasterizer in this process"
        else:
            try:
                options = {"max_views": settings.mask_check_views, **dict(settings.mask_check_options)}
                refine = mask_check(pipeline, scene, rasterize_fn, **options)
            except (OSError, ValueError) as error:
                reason = str(error)
        if refine is None and log is not None:
            log(
                f"Warning: the training masks are unavailable ({reason}); using the vote clustering without the mask "
                "check (--mask-check False does this on purpose)"
            )
    instances = cluster_levels(
        scene.means,
        scene.vote_offsets,
        scene.vote_support,
        scene.level_names,
        on_level=on_level,
        refine=refine,
        **settings.clustering.kwargs(),
        **dict(settings.cluster_options),
    )
    instances.validate()
    return instances, refine is not None or not settings.mask_check


def _write_record(instances: InstanceSet, run_dir: Path, key: Dict[str, str], settings: InstanceSettings) -> Path:
    """Write the record into a hidden sibling and rename it onto ``run_dir/RECORD_FOLDER``."""
    target = run_dir / RECORD_FOLDER
    sweep_leftovers(target)  # what killed writes left
    staging = make_temp_dir(target, ".partial")
    try:
        instances.save(
            staging,
            extra={
                "record": {
                    "format": RECORD_FORMAT,
                    "version": RECORD_VERSION,
                    "key": key,
                    "settings": settings.to_dict(),
                }
            },
        )
        replace_folder(staging, target)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return target


def run_instances(
    scene: TrainedScene,
    run_dir: Optional[Path],
    settings: InstanceSettings = InstanceSettings(),
    pipeline: Any = None,
    rasterize_fn: Optional[Callable[..., tuple]] = None,
    on_level: Optional[Callable[[int, str], None]] = None,
    log: Optional[Log] = None,
    masks_unavailable: Optional[str] = None,
) -> InstanceSet:
    """The instances of a trained run: read from ``run_dir``'s record when its key matches, else computed and kept.

    scene: the run's Gaussians and votes (:class:`~votesplat_ns.core.scene.TrainedScene`).
    run_dir: the folder of the run's config.yml (None: compute in memory, keep nothing).
    settings: the command's settings (:class:`InstanceSettings`).
    pipeline: the loaded nerfstudio pipeline (its datamanager gives the mask check its training views
        and masks); rasterize_fn: gsplat's ``rasterization`` signature (the check renders with it).
    on_level: called before each level is clustered (progress); log: one-line messages (rebuilds, warnings).
    masks_unavailable: why there is no ``pipeline`` (said in the warning that the mask check cannot run).
    """
    # nothing is kept (no folder, or the mask check cannot run), so no key is needed (5M Gaussians hash in ~1 s)
    if run_dir is None or (pipeline is None and settings.mask_check):
        return compute_instances(scene, settings, pipeline, rasterize_fn, on_level, log, masks_unavailable)[0]
    key = record_key(scene, settings, pipeline)
    target = Path(run_dir) / RECORD_FOLDER
    if target.is_dir():
        found = _read_record(target)
        if found is not None and found[0] == key:
            with contextlib.suppress(OSError, ValueError, KeyError):
                instances = InstanceSet.load(target)
                if instances.num_gaussians == scene.num_gaussians:
                    return instances
            if log is not None:
                log(f"The instances kept in {target} cannot be read; computing them again")
        elif log is not None:
            changed = [part for part in KEY_PARTS if found is None or found[0].get(part) != key[part]]
            what = (
                " and ".join(_WHAT_CHANGED[part] for part in changed) if found is not None else "an unreadable record"
            )
            log(f"The instances kept in {target} were computed for {what}; computing them again")
    instances, checked = compute_instances(scene, settings, pipeline, rasterize_fn, on_level, log, masks_unavailable)
    if checked:
        try:
            _write_record(instances, target.parent, key, settings)
        except OSError as error:
            if log is not None:
                log(
                    f"Warning: cannot keep the instances in {target} ({error.strerror or error}); they were computed "
                    "in memory and will be computed again next time"
                )
    return instances
