"""The instance dictionary (paper §3.4) and instance-id maps rendered for any camera.

Per vote level, every Gaussian has one instance id: 0..K-1 for the K instances, -1 for "in no
instance". A Gaussian is -1 either because it is background at that level (it received no vote
supervision) or because the clustering's noise rule left it out; ``foreground`` tells them apart.
A Gaussian that never voted but lies inside an object (hidden behind its surface in every view)
can join that object after the clustering (``core/whole_objects.py``); it then counts as foreground.
Invariants (``InstanceSet.validate``): background Gaussians are -1; each foreground Gaussian is in
exactly one instance or -1 (noise); ids are 0..K-1 with no gaps, and every instance is non-empty.

Files (``InstanceSet.save``): ``instances.json`` (human-readable manifest: levels, per instance the
count, bounding box of the Gaussian means, vote centre, parent, colour) and ``instance_ids.npz``
(per-Gaussian ids [L, N] int32 and foreground [L, N] bool). Both are written atomically.

Pure numpy/torch; no nerfstudio import.
"""

from __future__ import annotations

import colorsys
import io
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from votesplat_ns.core.ply_io import atomic_write, jsonable

if TYPE_CHECKING:
    from votesplat_ns.core.cameras import PinholeView
    from votesplat_ns.core.scene import TrainedScene

MANIFEST_NAME = "instances.json"
IDS_NAME = "instance_ids.npz"
MANIFEST_FORMAT = "votesplat-instances"
MANIFEST_VERSION = 1
NO_INSTANCE = -1
NO_INSTANCE_COLOR = (0, 0, 0)
_GOLDEN = 0.6180339887498949


def instance_colors(instance_ids) -> np.ndarray:
    """Stable RGB uint8 colours [..., 3] for instance ids (-1 -> black).

    The colour is a pure function of the id (golden-ratio hue steps, alternating saturation and
    value), so an instance has the same colour in every view, run and session.
    """
    ids = np.asarray(instance_ids.detach().cpu() if hasattr(instance_ids, "detach") else instance_ids).astype(np.int64)
    unique, inverse = np.unique(ids, return_inverse=True)
    table = np.zeros((unique.size, 3), dtype=np.uint8)
    for row, value in enumerate(unique.tolist()):
        if value < 0:
            table[row] = NO_INSTANCE_COLOR
            continue
        hue = (value * _GOLDEN) % 1.0
        saturation = (0.85, 0.55, 0.7)[value % 3]
        brightness = (0.95, 0.8)[(value // 3) % 2]
        table[row] = np.round(np.array(colorsys.hsv_to_rgb(hue, saturation, brightness)) * 255)
    return table[inverse.reshape(ids.shape)]


def size_confidence(counts, num_foreground: int) -> np.ndarray:
    """Fallback confidence per instance: its Gaussian count as a fraction of the level's foreground.

    HDBSCAN groups Gaussians whose votes agree on one centre; the more Gaussians agree, the more
    training views' masks stand behind the instance, while fragments and floaters are the small
    clusters that few Gaussians (few views) support. Only the order matters to a ranking metric
    (AP); dividing by the foreground count puts the value in [0, 1] for every scene.
    """
    counts = np.asarray(counts, dtype=np.float64)
    return counts / max(int(num_foreground), 1)


@dataclass
class LevelInstances:
    """The instances of one vote level."""

    name: str
    ids: np.ndarray  # [N] int64 instance id per Gaussian, -1 = none
    foreground: np.ndarray  # [N] bool, received vote supervision at this level or joined an instance as hidden
    counts: np.ndarray  # [K] int64 Gaussians per instance
    bbox_min: np.ndarray  # [K, 3] of the member Gaussians' means
    bbox_max: np.ndarray  # [K, 3]
    vote_centres: np.ndarray  # [K, 3] mean vote of the members that voted
    # None means "no parent": __post_init__ replaces it with the array, so readers always get one
    parents: np.ndarray = None  # pyright: ignore[reportAssignmentType]  # [K] int64 id at the parent level, -1 = none (or no parent level)
    parent_overlap: np.ndarray = None  # pyright: ignore[reportAssignmentType]  # [K] fraction of the instance's Gaussians inside its parent
    clustering: Dict[str, object] = field(default_factory=dict)
    # [K] float in [0, 1]: how sure the instance is an object (core/whole_objects.py instance_confidence), None
    # when the clustering gave none; scorers rank instances by :meth:`ranking_confidence`, which falls back to the size
    confidence: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        k = self.counts.shape[0]
        if self.parents is None:
            self.parents = np.full(k, -1, dtype=np.int64)
        if self.parent_overlap is None:
            self.parent_overlap = np.zeros(k, dtype=np.float64)

    @property
    def num_instances(self) -> int:
        return int(self.counts.shape[0])

    @property
    def num_noise(self) -> int:
        return int((self.foreground & (self.ids < 0)).sum())

    def ranking_confidence(self) -> np.ndarray:
        """[K] ``confidence`` when given, else :func:`size_confidence` of the level."""
        if self.confidence is not None:
            return np.asarray(self.confidence, dtype=np.float64)
        return size_confidence(self.counts, int(self.foreground.sum()))

    @classmethod
    def from_ids(
        cls,
        name: str,
        ids,
        foreground,
        means,
        votes,
        clustering: Optional[Dict[str, object]] = None,
        confidence: Optional[np.ndarray] = None,
    ) -> "LevelInstances":
        """Build a level from per-Gaussian ids [N] (0..K-1, -1), means [N, 3] and votes [N, 3]
        (``confidence``: [K] per instance, or None)."""
        ids = np.asarray(ids, dtype=np.int64)
        foreground = np.asarray(foreground, dtype=bool)
        means = np.asarray(means, dtype=np.float64)
        votes = np.asarray(votes, dtype=np.float64)
        members = np.flatnonzero(ids >= 0)
        k = int(ids[members].max()) + 1 if members.size else 0
        counts = np.bincount(ids[members], minlength=k).astype(np.int64)
        if (counts == 0).any():
            raise ValueError(
                f"level {name!r}: instance ids must be 0..K-1 without gaps; missing {np.flatnonzero(counts == 0).tolist()}"
            )
        order = members[np.argsort(ids[members], kind="stable")]
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        if k:
            bbox_min = np.minimum.reduceat(means[order], starts, axis=0)
            bbox_max = np.maximum.reduceat(means[order], starts, axis=0)
            # members without a vote (hidden Gaussians that joined an object after the
            # clustering) do not count; an instance with no vote at all takes its members' mean
            voted = np.asarray(np.isfinite(votes[order]).all(axis=1))
            vote_sums = np.add.reduceat(np.where(voted[:, None], votes[order], 0.0), starts, axis=0)
            num_voted = np.add.reduceat(voted.astype(np.int64), starts)
            mean_points = np.add.reduceat(means[order], starts, axis=0) / counts[:, None]
            vote_centres = np.where(num_voted[:, None] > 0, vote_sums / np.maximum(num_voted, 1)[:, None], mean_points)
        else:
            bbox_min = bbox_max = vote_centres = np.zeros((0, 3))
        if confidence is not None:
            confidence = np.asarray(confidence, dtype=np.float64)
            if confidence.shape != (k,):
                raise ValueError(f"level {name!r}: {confidence.shape[0]} confidences for {k} instances")
        return cls(
            name,
            ids,
            foreground,
            counts,
            bbox_min,
            bbox_max,
            vote_centres,
            clustering=dict(clustering or {}),
            confidence=confidence,
        )

    def members(self) -> Dict[int, np.ndarray]:
        """The dictionary of the paper: instance id -> sorted Gaussian indices."""
        members = np.flatnonzero(self.ids >= 0)
        order = members[np.argsort(self.ids[members], kind="stable")]
        return (
            {i: chunk for i, chunk in enumerate(np.split(order, np.cumsum(self.counts)[:-1]))}
            if self.num_instances
            else {}
        )

    def gaussian_indices(self, instance_id: int) -> np.ndarray:
        if not 0 <= instance_id < self.num_instances:
            raise ValueError(f"level {self.name!r} has instances 0..{self.num_instances - 1}, not {instance_id}")
        return np.flatnonzero(self.ids == instance_id)

    def link_parents(self, parent: "LevelInstances") -> None:
        """Parent of each instance = the ``parent``-level instance holding most of its Gaussians."""
        k = self.num_instances
        if k == 0:
            return
        inside = self.ids >= 0
        table = np.zeros((k, parent.num_instances + 1), dtype=np.int64)
        np.add.at(table, (self.ids[inside], parent.ids[inside] + 1), 1)
        # column 0 counts Gaussians that are in no parent instance; they cannot make a parent
        best = table[:, 1:].argmax(axis=1) if parent.num_instances else np.zeros(k, dtype=np.int64)
        best_count = table[np.arange(k), best + 1] if parent.num_instances else np.zeros(k, dtype=np.int64)
        self.parents = np.where(best_count > 0, best, -1).astype(np.int64)
        self.parent_overlap = best_count / self.counts

    def to_manifest(
        self, parent_level: Optional[str] = None, extra: Optional[Mapping[int, Mapping[str, object]]] = None
    ) -> Dict[str, Any]:
        """JSON-ready description; ``extra`` adds fields to instance entries (e.g. exported file)."""
        colors = instance_colors(np.arange(self.num_instances))
        instances = []
        for i in range(self.num_instances):
            entry = {
                "id": i,
                "count": int(self.counts[i]),
                "bbox_min": [float(v) for v in self.bbox_min[i]],
                "bbox_max": [float(v) for v in self.bbox_max[i]],
                "vote_centre": [float(v) for v in self.vote_centres[i]],
                "parent": int(self.parents[i]),
                "parent_overlap": float(self.parent_overlap[i]),
                "color": [int(c) for c in colors[i]],
            }
            if self.confidence is not None:
                entry["confidence"] = float(self.confidence[i])
            if extra and i in extra:
                entry.update(jsonable(extra[i]))
            instances.append(entry)
        return {
            "name": self.name,
            "parent_level": parent_level,
            "num_instances": self.num_instances,
            "num_foreground": int(self.foreground.sum()),
            "num_background": int((~self.foreground).sum()),
            "num_noise": self.num_noise,
            "clustering": jsonable(self.clustering),
            "instances": instances,
        }


def vote_level_index(level_names: Sequence[str], key: Union[int, str, None]) -> int:
    """Index in ``level_names`` of a level given by name, by index (also as a string: "1", "-1"), or None (the first)."""
    if key is None:
        key = 0
    if isinstance(key, str):
        if key in level_names:
            return list(level_names).index(key)
        if not key.lstrip("-").isdigit():
            raise ValueError(
                f"unknown vote level {key!r}; this model has levels {list(level_names)} (pass a name or an index)"
            )
    index = int(key)
    if not -len(level_names) <= index < len(level_names):
        raise ValueError(f"vote level index {index} out of range; this model has levels {list(level_names)}")
    return index % len(level_names)


@dataclass
class InstanceSet:
    """Instances of every vote level of one model."""

    levels: List[LevelInstances]
    num_gaussians: int
    # None means "each level's parent is the level before it": __post_init__ fills the list in
    parent_levels: List[Optional[str]] = None  # pyright: ignore[reportAssignmentType]

    def __post_init__(self) -> None:
        if self.parent_levels is None:
            self.parent_levels = [self.levels[i - 1].name if i > 0 else None for i in range(len(self.levels))]

    @property
    def level_names(self) -> tuple:
        return tuple(level.name for level in self.levels)

    def level(self, key: Union[int, str, None] = None) -> LevelInstances:
        """A level by name or index (None: the first level)."""
        return self.levels[self.level_index(key)]

    def level_index(self, key: Union[int, str, None]) -> int:
        return vote_level_index(self.level_names, key)

    def validate(self) -> None:
        """Raise ValueError if an invariant of the module docstring does not hold."""
        for index, level in enumerate(self.levels):
            n, k = self.num_gaussians, level.num_instances
            if level.ids.shape != (n,) or level.foreground.shape != (n,):
                raise ValueError(f"level {level.name!r}: ids/foreground must have shape [{n}]")
            if (level.ids < -1).any() or (level.ids >= k).any():
                raise ValueError(f"level {level.name!r}: ids must lie in -1..{k - 1}")
            if (level.ids[~level.foreground] != -1).any():
                raise ValueError(f"level {level.name!r}: a background Gaussian is assigned to an instance")
            counts = np.bincount(level.ids[level.ids >= 0], minlength=k)
            if not np.array_equal(counts, level.counts) or (counts == 0).any():
                raise ValueError(
                    f"level {level.name!r}: instance counts do not match the ids (or an instance is empty)"
                )
            if level.confidence is not None:
                confidence = np.asarray(level.confidence)
                if confidence.shape != (k,) or not np.isfinite(confidence).all():
                    raise ValueError(f"level {level.name!r}: confidence must be [{k}] finite numbers or None")
            parent_name = self.parent_levels[index]
            if parent_name is not None:
                parent_k = self.level(parent_name).num_instances
                if (level.parents < -1).any() or (level.parents >= parent_k).any():
                    raise ValueError(f"level {level.name!r}: parent ids must lie in -1..{parent_k - 1}")

    def to_manifest(
        self,
        instance_extra: Optional[Mapping[str, Mapping[int, Mapping[str, object]]]] = None,
        extra: Optional[Mapping[str, object]] = None,
    ) -> Dict[str, Any]:
        """The instances.json content; ``instance_extra[level][id]`` adds per-instance fields,
        ``extra`` adds top-level keys."""
        manifest: Dict[str, Any] = {
            "format": MANIFEST_FORMAT,
            "version": MANIFEST_VERSION,
            "num_gaussians": int(self.num_gaussians),
            "level_names": list(self.level_names),
            "ids_file": IDS_NAME,
            "levels": [
                level.to_manifest(self.parent_levels[i], (instance_extra or {}).get(level.name))
                for i, level in enumerate(self.levels)
            ],
        }
        if extra:
            manifest.update(jsonable(extra))
        return manifest

    def save(
        self,
        folder: Union[str, os.PathLike],
        instance_extra: Optional[Mapping[str, Mapping[int, Mapping[str, object]]]] = None,
        extra: Optional[Mapping[str, object]] = None,
    ) -> Dict[str, Any]:
        """Write instances.json and instance_ids.npz into ``folder`` (atomically); returns the manifest."""
        folder = Path(folder)
        manifest = self.to_manifest(instance_extra, extra)
        buffer = io.BytesIO()
        np.savez_compressed(
            buffer,
            level_names=np.array(self.level_names),
            ids=np.stack([level.ids for level in self.levels]).astype(np.int32)
            if self.levels
            else np.zeros((0, self.num_gaussians), np.int32),
            foreground=np.stack([level.foreground for level in self.levels])
            if self.levels
            else np.zeros((0, self.num_gaussians), bool),
        )
        with atomic_write(folder / IDS_NAME) as handle:
            handle.write(buffer.getvalue())
        with atomic_write(folder / MANIFEST_NAME) as handle:
            handle.write((json.dumps(manifest, indent=2) + "\n").encode("utf-8"))
        return manifest

    @classmethod
    def load(cls, folder: Union[str, os.PathLike]) -> "InstanceSet":
        """Read a set written by ``save`` (statistics from the manifest, ids from the npz)."""
        folder = Path(folder)
        manifest_path = folder / MANIFEST_NAME
        if not manifest_path.is_file():
            raise ValueError(f"{manifest_path} not found; point at a folder written by the votesplat instance export")
        manifest = json.loads(manifest_path.read_text())
        if manifest.get("format") != MANIFEST_FORMAT:
            raise ValueError(
                f"{manifest_path} is not a votesplat instance manifest (format={manifest.get('format')!r})"
            )
        with np.load(folder / manifest.get("ids_file", IDS_NAME)) as data:
            ids, foreground = data["ids"].astype(np.int64), data["foreground"].astype(bool)
        levels = []
        for index, entry in enumerate(manifest["levels"]):
            inst = entry["instances"]

            def arr(key: str, dtype: Any = np.float64) -> np.ndarray:
                return np.array([e[key] for e in inst], dtype=dtype).reshape(len(inst), -1)

            levels.append(
                LevelInstances(
                    name=entry["name"],
                    ids=ids[index],
                    foreground=foreground[index],
                    counts=arr("count", np.int64)[:, 0],
                    bbox_min=arr("bbox_min"),
                    bbox_max=arr("bbox_max"),
                    vote_centres=arr("vote_centre"),
                    parents=arr("parent", np.int64)[:, 0],
                    parent_overlap=arr("parent_overlap")[:, 0],
                    clustering=entry.get("clustering", {}),
                    # written only when the clustering gave one for every instance
                    confidence=arr("confidence")[:, 0] if inst and all("confidence" in e for e in inst) else None,
                )
            )
        return cls(
            levels=levels,
            num_gaussians=int(manifest["num_gaussians"]),
            parent_levels=[e.get("parent_level") for e in manifest["levels"]],
        )


RasterizeFn = Callable[..., tuple]


@torch.no_grad()
def render_instance_ids(
    rasterize_fn: RasterizeFn,
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    instance_ids,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    min_weight: float = 0.5,
    channels_per_pass: int = 32,
    **rasterize_kwargs,
) -> torch.Tensor:
    """Instance id map [H, W] (int64, -1 = none) of the Gaussians seen from one camera.

    Each instance is rasterised as a one-hot colour channel (all Gaussians take part, so
    background Gaussians still occlude), giving per pixel the accumulated weight
    w_k = sum over the instance's Gaussians of alpha_i * T_i. The pixel gets argmax_k w_k if that
    weight is at least ``min_weight``, else -1. The default 0.5 means "this instance makes up the
    majority of the pixel's colour": such an instance is unique, so no tie-breaking is involved,
    and pixels blended from several instances, background or empty space are left out (good for
    cutting CLIP crops). ``channels_per_pass`` instances are rendered per rasteriser call.

    ``rasterize_fn`` has the signature of gsplat 1.4's ``rasterization`` (means, quats, scales,
    opacities [N], colors [N, D], viewmats [1, 4, 4], Ks [1, 3, 3], width, height, ...) ->
    (colors [1, H, W, D], alphas, info); scales are linear, opacities in [0, 1], viewmat
    world-to-camera (OpenCV).
    """
    if not 0.0 < min_weight <= 1.0:
        raise ValueError(f"min_weight must be in (0, 1], got {min_weight}")
    if channels_per_pass < 1:
        raise ValueError(f"channels_per_pass must be >= 1, got {channels_per_pass}")
    device = means.device
    ids = (
        torch.as_tensor(np.asarray(instance_ids) if not torch.is_tensor(instance_ids) else instance_ids, device=device)
        .long()
        .reshape(-1)
    )
    if ids.shape[0] != means.shape[0]:
        raise ValueError(f"instance_ids has {ids.shape[0]} entries for {means.shape[0]} Gaussians")
    opacities = opacities.reshape(-1)
    best_weight = torch.zeros(height, width, device=device)
    best_id = torch.full((height, width), -1, dtype=torch.long, device=device)
    unique = torch.unique(ids[ids >= 0])
    if unique.numel() == 0:
        return best_id
    compact = torch.searchsorted(unique, ids.clamp(min=0))
    compact[ids < 0] = -1
    viewmats, Ks = viewmat.reshape(1, 4, 4).to(means), K.reshape(1, 3, 3).to(means)
    for start in range(0, unique.numel(), channels_per_pass):
        stop = min(start + channels_per_pass, unique.numel())
        inside = (compact >= start) & (compact < stop)
        colors = torch.zeros(means.shape[0], stop - start, device=device, dtype=means.dtype)
        colors[inside, compact[inside] - start] = 1.0
        rendered, _, _ = rasterize_fn(
            means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree=None, **rasterize_kwargs
        )
        weight, channel = rendered[0].max(dim=-1)
        better = weight > best_weight
        best_weight = torch.where(better, weight, best_weight)
        best_id = torch.where(better, unique[start + channel], best_id)
    return torch.where(best_weight >= min_weight, best_id, torch.full_like(best_id, -1))


def render_id_maps(
    scene: "TrainedScene",
    gaussian_ids,
    views: Sequence["PinholeView"],
    rasterize_fn: RasterizeFn,
    out_sizes: Optional[Sequence[Tuple[int, int]]] = None,
    min_weight: float = 0.5,
    device: Union[str, torch.device, None] = None,
    on_view: Optional[Callable[[], Any]] = None,
) -> List[np.ndarray]:
    """Instance-id map per view (int64, -1 = none) of a scene's finite Gaussians, rendered at ``out_sizes`` (H, W) if given.

    ``gaussian_ids`` [N] per Gaussian of ``scene``; ``device`` defaults to the scene's; ``on_view`` is
    called after each view (progress). Rendering at another size scales the intrinsics, which is
    exact in the continuous pixel frame.
    """
    keep = scene.finite()
    means, quats, scales, opacities = scene.gaussians(keep, device)[:4]
    ids = torch.as_tensor(np.asarray(gaussian_ids), device=means.device).long()[
        torch.as_tensor(keep, device=means.device)
    ]
    maps = []
    for index, view in enumerate(views):
        height, width = out_sizes[index] if out_sizes is not None else (view.height, view.width)
        K = view.K.clone().float()
        K[0] *= width / view.width
        K[1] *= height / view.height
        id_map = render_instance_ids(
            rasterize_fn,
            means,
            quats,
            scales,
            opacities,
            ids,
            view.viewmat.float().to(means.device),
            K.to(means.device),
            int(width),
            int(height),
            min_weight=min_weight,
        )
        maps.append(id_map.cpu().numpy())
        if on_view is not None:
            on_view()
    return maps


def instance_picture(id_maps: Sequence, images: Optional[Sequence] = None, gap: int = 4) -> np.ndarray:
    """One uint8 picture [H, W, 3]: views side by side, RGB images (if given) above their id maps."""
    if len(id_maps) == 0:
        raise ValueError("instance_picture needs at least one id map")
    if images is not None and len(images) != len(id_maps):
        raise ValueError(f"{len(images)} images for {len(id_maps)} id maps; pass one image per view")
    rows = [[instance_colors(m) for m in id_maps]]
    if images is not None:
        row = []
        for image in images:
            image = np.asarray(image.detach().cpu() if hasattr(image, "detach") else image)
            if image.dtype != np.uint8:
                image = (np.clip(image.astype(np.float64), 0.0, 1.0) * 255 + 0.5).astype(np.uint8)
            row.append(image[..., :3])
        rows.insert(0, row)
    widths = [max(row[c].shape[1] for row in rows) for c in range(len(id_maps))]
    heights = [max(tile.shape[0] for tile in row) for row in rows]
    canvas = np.full(
        (sum(heights) + gap * (len(rows) - 1), sum(widths) + gap * (len(widths) - 1), 3), 255, dtype=np.uint8
    )
    y = 0
    for row, row_height in zip(rows, heights):
        x = 0
        for tile, column_width in zip(row, widths):
            canvas[y : y + tile.shape[0], x : x + tile.shape[1]] = tile
            x += column_width + gap
        y += row_height + gap
    return canvas


def save_instance_picture(
    path: Union[str, os.PathLike], id_maps: Sequence, images: Optional[Sequence] = None, gap: int = 4
) -> np.ndarray:
    """Save ``instance_picture`` as a PNG (atomically); returns the picture."""
    from PIL import Image

    picture = instance_picture(id_maps, images, gap)
    buffer = io.BytesIO()
    Image.fromarray(picture).save(buffer, format="PNG")
    with atomic_write(path) as handle:
        handle.write(buffer.getvalue())
    return picture
