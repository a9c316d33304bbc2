"""Seeded corruption of label images, to stand in for imperfect SAM masks (pure numpy).

Label images are integer [H,W] arrays, 0 = no mask, k > 0 = mask k. :class:`MaskNoise` applies, in
this order and each to every mask independently with its rate as probability:

1. drop: the mask disappears (its pixels become 0);
2. merge (under-segmentation): the mask absorbs one other mask within ``merge_max_gap_px`` pixels
   (chessboard distance; 1 = touching); a mask takes part in at most one merge per view;
3. split (over-segmentation): the mask is cut along a random straight line through its centroid;
   the far side gets a new id (max id + 1, + 2, ...);
4. jitter: the mask grows (dilation, may cover neighbours) or shrinks (erosion, pixels become 0) by
   a random 1..``max_jitter_px`` pixels, 8-connected; the image border never erodes a mask.

Randomness: every (seed, view index, kind of noise) has its own stream, so a view's noise does not
depend on the other views, and changing one rate never changes the decisions of the other kinds.
All rates 0 returns an unchanged copy.
"""

from __future__ import annotations

import dataclasses
import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import List, Sequence, Tuple, Union

import numpy as np

from votesplat_ns.core.ply_io import make_temp_dir, replace_folder
from votesplat_ns.eval.ground_truth import GT_LEVELS, GroundTruthDataset, write_json_atomic

_DROP, _MERGE, _SPLIT, _JITTER = 1, 2, 3, 4


def dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """Binary dilation by a (2r+1)x(2r+1) square (chessboard distance <= r)."""
    out = np.asarray(mask, dtype=bool)
    for _ in range(int(radius)):
        padded = np.pad(out, 1, mode="constant", constant_values=False)
        h, w = out.shape
        grown = np.zeros_like(out)
        for dy in (0, 1, 2):
            for dx in (0, 1, 2):
                grown |= padded[dy : dy + h, dx : dx + w]
        out = grown
    return out


def erode(mask: np.ndarray, radius: int) -> np.ndarray:
    """Binary erosion by a (2r+1)x(2r+1) square; outside the image counts as inside the mask."""
    out = np.asarray(mask, dtype=bool)
    for _ in range(int(radius)):
        padded = np.pad(out, 1, mode="edge")
        h, w = out.shape
        kept = np.ones_like(out)
        for dy in (0, 1, 2):
            for dx in (0, 1, 2):
                kept &= padded[dy : dy + h, dx : dx + w]
        out = kept
    return out


@dataclass(frozen=True)
class NoiseEvent:
    kind: str  # "drop" | "merge" | "split" | "jitter"
    label: int  # the mask acted on (for "merge": the mask that stays)
    other: int = 0  # "merge": the absorbed mask; "split": the new id
    amount: int = 0  # "jitter": +r grown / -r shrunk
    line: Tuple[float, float, float] = (0.0, 0.0, 0.0)  # "split": (nx, ny, c); new id where nx*x + ny*y > c


def _check_rate(name: str, value: float) -> None:
    try:
        ok = 0.0 <= float(value) <= 1.0  # False for NaN
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"{name} must be a probability in [0, 1] (got {value!r})")


@dataclass(frozen=True)
class MaskNoise:
    split_rate: float = 0.0
    merge_rate: float = 0.0
    jitter_rate: float = 0.0
    drop_rate: float = 0.0
    max_jitter_px: int = 2
    merge_max_gap_px: int = 2
    seed: int = 0

    def __post_init__(self):
        for name in ("split_rate", "merge_rate", "jitter_rate", "drop_rate"):
            _check_rate(name, getattr(self, name))
        if int(self.max_jitter_px) < 1:
            raise ValueError(f"max_jitter_px must be at least 1 (got {self.max_jitter_px})")
        if int(self.merge_max_gap_px) < 1:
            raise ValueError(f"merge_max_gap_px must be at least 1, i.e. touching (got {self.merge_max_gap_px})")

    def _rng(self, view_index: int, kind: int) -> np.random.Generator:
        return np.random.default_rng([int(self.seed), int(view_index), kind])

    def apply(self, labels: np.ndarray, view_index: int = 0) -> np.ndarray:
        return self.apply_with_events(labels, view_index)[0]

    def apply_with_events(self, labels: np.ndarray, view_index: int = 0) -> Tuple[np.ndarray, List[NoiseEvent]]:
        """Noisy copy of ``labels`` (same dtype) and the list of what was done, in order."""
        labels = np.asarray(labels)
        if labels.ndim != 2:
            raise ValueError(f"labels must be a 2D [H,W] label image (got shape {labels.shape})")
        if not np.issubdtype(labels.dtype, np.integer):
            raise ValueError(f"labels must be integer ids (got dtype {labels.dtype}); cast with .astype(np.int32)")
        if labels.size and labels.min() < 0:
            raise ValueError("labels has negative ids; use 0 for 'no mask' and k > 0 for masks")
        out = labels.astype(np.int64)
        events: List[NoiseEvent] = []
        if self.drop_rate > 0:
            self._drop(out, self._rng(view_index, _DROP), events)
        if self.merge_rate > 0:
            self._merge(out, self._rng(view_index, _MERGE), events)
        if self.split_rate > 0:
            self._split(out, self._rng(view_index, _SPLIT), events)
        if self.jitter_rate > 0:
            self._jitter(out, self._rng(view_index, _JITTER), events)
        if out.size and out.max() > np.iinfo(labels.dtype).max:
            raise ValueError(f"split ids exceed the range of {labels.dtype}; pass a wider label dtype (e.g. int32)")
        return out.astype(labels.dtype), events

    def apply_to_views(self, label_images: Sequence[np.ndarray]) -> List[np.ndarray]:
        return [self.apply(image, view_index=i) for i, image in enumerate(label_images)]

    @staticmethod
    def _ids(out: np.ndarray) -> List[int]:
        return [int(v) for v in np.unique(out) if v > 0]

    def _drop(self, out, rng, events):
        for label in self._ids(out):
            if rng.random() < self.drop_rate:
                out[out == label] = 0
                events.append(NoiseEvent("drop", label))

    def _merge(self, out, rng, events):
        used = set()
        for label in self._ids(out):
            decide = rng.random()
            if label in used or decide >= self.merge_rate:
                continue
            near = dilate(out == label, self.merge_max_gap_px)
            candidates = sorted(set(int(v) for v in np.unique(out[near])) - {0, label} - used)
            if not candidates:
                continue
            other = candidates[int(rng.integers(len(candidates)))]
            out[out == other] = label
            used.update((label, other))
            events.append(NoiseEvent("merge", label, other=other))

    def _split(self, out, rng, events):
        next_id = int(out.max()) + 1 if out.size else 1
        for label in self._ids(out):
            decide = rng.random()
            angle = rng.uniform(0.0, math.pi)
            if decide >= self.split_rate:
                continue
            ys, xs = np.nonzero(out == label)
            if len(xs) < 2:
                continue
            cx, cy = xs.mean(), ys.mean()
            for attempt in range(8):
                theta = angle + attempt * math.pi / 8
                nx, ny = math.cos(theta), math.sin(theta)
                c = nx * cx + ny * cy
                far = nx * xs + ny * ys > c
                if far.any() and not far.all():
                    break
            else:
                continue
            out[ys[far], xs[far]] = next_id
            events.append(NoiseEvent("split", label, other=next_id, line=(nx, ny, c)))
            next_id += 1

    def _jitter(self, out, rng, events):
        for label in self._ids(out):
            decide = rng.random()
            radius = int(rng.integers(1, int(self.max_jitter_px) + 1))
            grow = bool(rng.random() < 0.5)
            if decide >= self.jitter_rate:
                continue
            mask = out == label
            if grow:
                out[dilate(mask, radius) & ~mask] = label
            else:
                out[mask & ~erode(mask, radius)] = 0
            events.append(NoiseEvent("jitter", label, amount=radius if grow else -radius))


SAM_LIKE_NOISE = MaskNoise(split_rate=0.15, merge_rate=0.1, jitter_rate=0.5, drop_rate=0.05)
"""The benchmarks' "noisy masks" and ``votesplat eval noise``'s defaults: SAM's typical errors at rates that keep a
mask's identity in most views (MaskNoise() itself changes nothing)."""


# ----------------------------------------------------------------------------- noisy mask folders

NOISE_MANIFEST_NAME = "noise.json"


def write_noisy_masks(
    data: Union[str, Path],
    output: Union[str, Path],
    noise: MaskNoise,
    levels: Sequence[str] = GT_LEVELS,
    overwrite: bool = False,
) -> Path:
    """GT label images with ``noise`` applied, as ``<output>/<level>/<image_stem>.png`` (+ noise.json).

    Every frame of the dataset is written (view index = frame order in transforms.json, so the
    noise of a view is reproducible); each level gets its own seed (``noise.seed + level index``).
    The folder is built beside ``output`` and renamed into place; an existing ``output`` is
    replaced only with ``overwrite`` and only if it holds a previous noisy-mask folder.
    """
    from votesplat_ns.eval.synthetic.dataset_files import write_png

    dataset = GroundTruthDataset.open(data)
    levels = tuple(levels)
    missing = [level for level in levels if level not in dataset.levels]
    if missing:
        raise ValueError(f"dataset {dataset.root} has no {missing} ground truth (it has {list(dataset.levels)})")
    if not levels:
        raise ValueError("pass at least one level (instance, part)")
    output = Path(output)
    if output.exists():
        if not output.is_dir():
            raise ValueError(f"{output} is a file; pass a folder path")
        if any(output.iterdir()):
            if not (output / NOISE_MANIFEST_NAME).is_file():
                raise ValueError(
                    f"{output} is a non-empty folder that is not a noisy-mask folder; choose a new or empty folder"
                )
            if not overwrite:
                raise ValueError(f"{output} already holds noisy masks; pass --overwrite to replace them")
    if output.resolve() == dataset.root.resolve() or dataset.root.resolve() in output.resolve().parents:
        raise ValueError(f"{output} lies inside the dataset {dataset.root}; write the noisy masks outside it")
    output.parent.mkdir(parents=True, exist_ok=True)
    staging = make_temp_dir(output, ".partial")
    try:
        changed = {level: 0 for level in levels}
        for level_index, level in enumerate(levels):
            level_noise = dataclasses.replace(noise, seed=int(noise.seed) + level_index)
            for view_index, name in enumerate(dataset.frames):
                clean = dataset.labels(name, level)
                noisy = level_noise.apply(clean.astype(np.int64), view_index=view_index)
                if noisy.max(initial=0) > np.iinfo(np.uint16).max:
                    raise ValueError(f"view {name} has more than 65535 masks after noise")
                changed[level] += int(not np.array_equal(noisy, clean))
                write_png(staging / level / f"{Path(name).stem}.png", noisy.astype(np.uint16))
        manifest = {
            "format": "votesplat-noisy-masks",
            "dataset": str(dataset.root),
            "levels": list(levels),
            "noise": dataclasses.asdict(noise),
            "level_seeds": {level: int(noise.seed) + i for i, level in enumerate(levels)},
            "num_views": len(dataset.frames),
            "views_changed": changed,
        }
        write_json_atomic(staging / NOISE_MANIFEST_NAME, manifest)
        replace_folder(staging, output)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return output
