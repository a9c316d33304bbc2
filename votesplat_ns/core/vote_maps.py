"""2D vote construction (VoteSplat paper, Sec. 3.2, Eq. 3-4): from mask label images to vote maps.

Pure numpy/torch; no nerfstudio import.

Conventions
-----------
- A *label image* is an integer array [H, W]: 0 = no mask, k > 0 = mask k.
- A *centroid table* is float32 [K+1, 2] holding (column, row) per label; row 0 (no mask) is NaN.
- Centroids are in pixel-INDEX coordinates: the paper's c_x = round(sum x*M / sum M) with
  x = 0..W-1. gsplat's continuous pixel frame puts the centre of pixel column x at x + 0.5, so a
  vote target in that frame is ``centroid + 0.5`` (see :func:`to_continuous`).
- Rounding (Eq. 3-4) is round-half-away-from-zero (``floor(v + 0.5)`` for the non-negative means
  that occur here): a mean of 2.5 gives 3. numpy's default banker's rounding would send 2.5 to 2
  but 3.5 to 4, i.e. ties would go to whichever neighbour is even, a position-dependent bias.
- Vote maps are stored compactly: one label image per level plus a centroid table per level;
  dense [H, W, 2] float targets are only expanded on demand.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional, Sequence, Tuple, Union, overload

import numpy as np
import torch

LABEL_DTYPE_COMPACT = np.uint16
"""Label stacks whose largest label fits in uint16 are stored as uint16 (half the size of int32)."""

BORDER_MASK_RULES = ("vote", "mask_only", "drop")
"""What a mask touching the image border becomes (see :func:`mask_centroids`)."""
DEFAULT_BORDER_MASKS = "vote"


def round_half_away_from_zero(values: np.ndarray) -> np.ndarray:
    """Round to the nearest integer; exact halves go away from zero (2.5 -> 3, -2.5 -> -3)."""
    values = np.asarray(values, dtype=np.float64)
    return np.sign(values) * np.floor(np.abs(values) + 0.5)


def _check_label_image(labels: np.ndarray, name: str = "labels") -> np.ndarray:
    labels = np.asarray(labels)
    if labels.ndim != 2:
        raise ValueError(f"{name} must be a 2D label image [H, W], got shape {tuple(labels.shape)}")
    if labels.dtype == np.bool_ or not np.issubdtype(labels.dtype, np.integer):
        raise ValueError(f"{name} must hold integer mask ids (0 = no mask), got dtype {labels.dtype}")
    if labels.size and labels.min() < 0:
        raise ValueError(f"{name} holds negative ids; use 0 for 'no mask' and 1..K for masks")
    return labels


def labels_from_binary_masks(masks: Sequence[np.ndarray], shape: Optional[Tuple[int, int]] = None) -> np.ndarray:
    """Merge possibly overlapping binary masks into one label image (int32 [H, W]).

    Overlap rule: masks are painted from the largest area to the smallest, so where masks
    overlap the SMALLER mask wins (a part stays visible on top of the object that contains it).
    Masks of equal area: the one EARLIER in ``masks`` wins. The rule depends only on the masks,
    so the result is deterministic.

    Label k (k >= 1) is ``masks[k - 1]``; a mask entirely covered by smaller ones leaves no
    pixels, so ids may have gaps (:func:`mask_centroids` renumbers compactly).

    Args:
        masks: boolean arrays [H, W] (any array where non-zero means inside).
        shape: (H, W); required only when ``masks`` is empty.
    """
    if len(masks) == 0:
        if shape is None:
            raise ValueError("labels_from_binary_masks got no masks; pass shape=(H, W) to get an empty label image")
        return np.zeros(shape, dtype=np.int32)
    stacked = [np.asarray(m) for m in masks]
    first_shape = stacked[0].shape
    for i, m in enumerate(stacked):
        if m.ndim != 2 or m.shape != first_shape:
            raise ValueError(f"mask {i} has shape {m.shape}, expected a 2D mask of shape {first_shape} like mask 0")
    if shape is not None and tuple(shape) != tuple(first_shape):
        raise ValueError(f"masks have shape {first_shape} but shape={tuple(shape)} was given")
    if len(stacked) >= np.iinfo(np.int32).max:
        raise ValueError("too many masks for an int32 label image")
    bool_masks = [m.astype(bool, copy=False) for m in stacked]
    areas = np.array([int(m.sum()) for m in bool_masks], dtype=np.int64)
    indices = np.arange(len(bool_masks))
    # lexsort sorts by the last key first: descending area, then descending input index, so
    # among equal areas the earliest mask is painted last and wins.
    paint_order = np.lexsort((-indices, -areas))
    labels = np.zeros(first_shape, dtype=np.int32)
    for i in paint_order:
        labels[bool_masks[i]] = i + 1
    return labels


def mask_centroids(labels: np.ndarray, border_masks: str = DEFAULT_BORDER_MASKS) -> Tuple[np.ndarray, np.ndarray]:
    """Per-mask centroids of a label image (paper Eq. 3-4).

    Args:
        labels: integer label image [H, W], 0 = no mask.
        border_masks: what a mask touching the first/last row or column becomes. The centroid
            of its visible part is not the object's, but the object is still an object:
            - "vote": kept, its visible part's centroid is the vote target (the official
              VoteSplat preprocessing);
            - "mask_only": kept as a mask (its pixels count as inside a mask, e.g. for the
              foreground rule) with no vote target: its centroid is NaN;
            - "drop": removed, its pixels become 0 (the paper's text filters masks that leave
              the field of view; an object cut by the frame in most views then looks like
              background there).

    Returns:
        labels_out: int32 [H, W], masks renumbered 1..K in increasing order of their input id;
            dropped masks become 0.
        centroids: float32 [K+1, 2], (column, row) in pixel-index coordinates, each rounded
            half away from zero; row 0 is NaN, and so is the row of a "mask_only" border mask.
    """
    if border_masks not in BORDER_MASK_RULES:
        raise ValueError(f"border_masks must be one of {', '.join(BORDER_MASK_RULES)}, got {border_masks!r}")
    labels = _check_label_image(labels)
    height, width = labels.shape
    max_id = int(labels.max()) if labels.size else 0
    # ids up to a few times the pixel count: histogram and lookup table (several times faster
    # than np.unique's sort at full resolution); sparse huge ids: sort and search instead
    dense_ids = max_id <= 4 * labels.size + 65536
    if dense_ids:
        ids = np.flatnonzero(np.bincount(labels.ravel(), minlength=max_id + 1))
    else:
        ids = np.unique(labels)
    ids = ids[ids > 0]
    touching = np.zeros(0, dtype=ids.dtype)
    if border_masks != "vote" and ids.size and labels.size:
        border = np.concatenate([labels[0, :], labels[-1, :], labels[:, 0], labels[:, -1]])
        touching = np.intersect1d(ids, border)
        if border_masks == "drop":
            ids = np.setdiff1d(ids, touching, assume_unique=True)
    num_masks = int(ids.size)
    if ids.size and dense_ids:
        # lookup table from input id to compact id (0 for dropped / absent ids)
        lut = np.zeros(max_id + 1, dtype=np.int32)
        lut[ids] = np.arange(1, num_masks + 1, dtype=np.int32)
        labels_out = lut[labels]
    elif ids.size:
        position = np.minimum(np.searchsorted(ids, labels), num_masks - 1)
        labels_out = np.where(ids[position] == labels, position + 1, 0).astype(np.int32)
    else:
        labels_out = np.zeros((height, width), dtype=np.int32)

    centroids = np.full((num_masks + 1, 2), np.nan, dtype=np.float32)
    if num_masks:
        flat = labels_out.ravel()
        cols = np.tile(np.arange(width, dtype=np.float64), height)
        rows = np.repeat(np.arange(height, dtype=np.float64), width)
        counts = np.bincount(flat, minlength=num_masks + 1)[1:].astype(np.float64)
        sum_x = np.bincount(flat, weights=cols, minlength=num_masks + 1)[1:]
        sum_y = np.bincount(flat, weights=rows, minlength=num_masks + 1)[1:]
        centroids[1:, 0] = round_half_away_from_zero(sum_x / counts)
        centroids[1:, 1] = round_half_away_from_zero(sum_y / counts)
        if border_masks == "mask_only" and touching.size:
            centroids[1 + np.searchsorted(ids, touching)] = np.nan
    return labels_out, centroids


@overload
def to_continuous(centroids_index: np.ndarray) -> np.ndarray: ...


@overload
def to_continuous(centroids_index: torch.Tensor) -> torch.Tensor: ...


def to_continuous(centroids_index: Union[np.ndarray, torch.Tensor]) -> Union[np.ndarray, torch.Tensor]:
    """Pixel-index coordinates -> gsplat's continuous pixel frame (pixel centre at index + 0.5)."""
    return centroids_index + 0.5


@dataclass
class VoteMaps:
    """The 2D votes of one view at all mask levels, stored compactly.

    Attributes:
        labels: [L, H, W] integer label images (uint16 or int32; may be a read-only memmap).
        centroids: L centroid tables, float32 [K_l+1, 2], (column, row) in pixel-index
            coordinates, row 0 NaN.
        level_names: optional names of the L levels.
    """

    labels: np.ndarray
    centroids: List[np.ndarray]
    level_names: Tuple[str, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        if self.labels.ndim != 3:
            raise ValueError(f"VoteMaps.labels must be [L, H, W], got shape {tuple(self.labels.shape)}")
        if self.labels.dtype not in (np.uint16, np.int32):
            raise ValueError(f"VoteMaps.labels must be uint16 or int32, got {self.labels.dtype}")
        if len(self.centroids) != self.labels.shape[0]:
            raise ValueError(
                f"VoteMaps has {self.labels.shape[0]} label levels but {len(self.centroids)} centroid tables"
            )
        self.centroids = [np.asarray(c, dtype=np.float32) for c in self.centroids]
        for level, table in enumerate(self.centroids):
            if table.ndim != 2 or table.shape[1] != 2 or table.shape[0] < 1:
                raise ValueError(f"centroid table of level {level} must be [K+1, 2], got {tuple(table.shape)}")
        self.level_names = tuple(self.level_names)
        if self.level_names and len(self.level_names) != self.labels.shape[0]:
            raise ValueError(f"{len(self.level_names)} level names for {self.labels.shape[0]} levels")

    @property
    def num_levels(self) -> int:
        return int(self.labels.shape[0])

    @property
    def height(self) -> int:
        return int(self.labels.shape[1])

    @property
    def width(self) -> int:
        return int(self.labels.shape[2])

    def num_masks(self, level: int) -> int:
        return int(self.centroids[level].shape[0] - 1)

    def targets(self, level: int) -> Tuple[np.ndarray, np.ndarray]:
        """Dense vote map of one level in pixel-index coordinates.

        Returns:
            votes: float32 [H, W, 2], (column, row) of the pixel's mask centroid; NaN outside masks
                and in masks without a vote target.
            valid: bool [H, W], True where the pixel carries a vote (a mask with a finite centroid).
        """
        labels = np.asarray(self.labels[level]).astype(np.int64)
        table = self.centroids[level]
        if labels.size and labels.max() >= table.shape[0]:
            raise ValueError(
                f"level {level} has label {int(labels.max())} but only {table.shape[0] - 1} centroids; the vote map is inconsistent"
            )
        votes = table[labels]
        return votes, np.isfinite(votes[..., 0])

    def targets_continuous(self, level: int) -> Tuple[np.ndarray, np.ndarray]:
        """Like :meth:`targets` but in gsplat's continuous pixel frame (pixel centre = index + 0.5)."""
        votes, valid = self.targets(level)
        return to_continuous(votes), valid

    def padded_centroids(self) -> np.ndarray:
        """All levels' centroid tables as one float32 [L, Kmax+1, 2] array, padded with NaN."""
        kmax = max(table.shape[0] for table in self.centroids)
        out = np.full((self.num_levels, kmax, 2), np.nan, dtype=np.float32)
        for level, table in enumerate(self.centroids):
            out[level, : table.shape[0]] = table
        return out


def stack_labels(label_images: Sequence[np.ndarray]) -> np.ndarray:
    """Stack L label images into [L, H, W], uint16 when every id fits, else int32."""
    if len(label_images) == 0:
        raise ValueError("need at least one label image (one per mask level)")
    shapes = {np.asarray(im).shape for im in label_images}
    if len(shapes) != 1:
        raise ValueError(f"label images of one view must share one size, got shapes {sorted(shapes)}")
    stacked = np.stack([np.asarray(im) for im in label_images])
    return stacked.astype(_label_dtype(stacked, LABEL_DTYPE_COMPACT))


def _label_dtype(labels: np.ndarray, compact: type) -> type:
    """``compact`` when every id of ``labels`` fits in it, else int32 (raises past int32)."""
    max_id = int(labels.max()) if labels.size else 0
    if max_id > np.iinfo(np.int32).max:
        raise ValueError(f"label id {max_id} does not fit in int32")
    return compact if max_id <= np.iinfo(compact).max else np.int32


def vote_maps_from_labels(
    label_images: Sequence[np.ndarray],
    border_masks: str = DEFAULT_BORDER_MASKS,
    level_names: Sequence[str] = (),
) -> VoteMaps:
    """Build a view's vote maps from one label image per level (runs :func:`mask_centroids` per level)."""
    outputs = [
        mask_centroids(_check_label_image(im, f"label image of level {i}"), border_masks)
        for i, im in enumerate(label_images)
    ]
    labels = stack_labels([lab for lab, _ in outputs])
    return VoteMaps(labels=labels, centroids=[c for _, c in outputs], level_names=tuple(level_names))


def nearest_source_indices(old_size: int, new_size: int) -> np.ndarray:
    """For each of ``new_size`` output pixels, the source pixel whose cell contains its centre.

    Output pixel j has its centre at (j + 0.5) in the output's continuous frame, i.e. at
    (j + 0.5) * old/new in the source frame; the source pixel containing it is the floor.
    """
    if old_size <= 0 or new_size <= 0:
        raise ValueError(f"sizes must be positive, got old={old_size}, new={new_size}")
    centres = (np.arange(new_size, dtype=np.float64) + 0.5) * (old_size / new_size)
    return np.clip(np.floor(centres).astype(np.int64), 0, old_size - 1)


def resize_label_images(labels: np.ndarray, new_h: int, new_w: int) -> np.ndarray:
    """Nearest-neighbour resize of [..., H, W] label images (ids are never blended)."""
    labels = np.asarray(labels)
    rows = nearest_source_indices(labels.shape[-2], new_h)
    cols = nearest_source_indices(labels.shape[-1], new_w)
    return labels[..., rows[:, None], cols[None, :]]


def resize_vote_maps(vote_maps: VoteMaps, new_h: int, new_w: int) -> VoteMaps:
    """Vote maps at another resolution (e.g. when nerfstudio downscaled the images).

    Labels are resampled nearest-neighbour (:func:`resize_label_images`); centroids follow the
    same map in the continuous frame, (c + 0.5) * s - 0.5 with s = new/old per axis, so a
    centroid keeps pointing at the same spot of the scene. Resized centroids are generally not
    integers; that is intended.
    """
    new_h, new_w = int(new_h), int(new_w)
    if new_h <= 0 or new_w <= 0:
        raise ValueError(f"resize_vote_maps needs a positive size, got {new_h}x{new_w}")
    if (new_h, new_w) == (vote_maps.height, vote_maps.width):
        return vote_maps
    scale = np.array([new_w / vote_maps.width, new_h / vote_maps.height], dtype=np.float64)
    labels = resize_label_images(vote_maps.labels, new_h, new_w)
    centroids = [((table.astype(np.float64) + 0.5) * scale - 0.5).astype(np.float32) for table in vote_maps.centroids]
    return VoteMaps(labels=np.ascontiguousarray(labels), centroids=centroids, level_names=vote_maps.level_names)


def label_tensor(labels: np.ndarray) -> torch.Tensor:
    """A view's [L, H, W] mask ids as a training batch carries them: int16 while every id fits (up to 32767
    masks a level; SAM makes hundreds), else int32. Half of int32's bytes in the vote maps kept in memory and
    in each vote step's copy to the GPU; every reader widens the ids it looks up."""
    labels = np.asarray(labels)
    # int16, not the cache's uint16: torch has few ops for uint16 tensors
    return torch.from_numpy(np.ascontiguousarray(labels, dtype=_label_dtype(labels, np.int16)))


def voting_pixels(vote_labels: torch.Tensor, vote_centroids: torch.Tensor) -> torch.Tensor:
    """int32 [C]: the flat indices (row * W + column), ascending, of the pixels that carry a vote at
    some level (their mask there has a finite centroid), from the datamanager's [L, H, W] labels and
    [L, K+1, 2] NaN-padded centroids. Training samples its vote pixels among these. (int32: half of
    int64's bytes, and a view's pixels are counted far below 2**31.)"""
    if vote_labels[0].numel() > np.iinfo(np.int32).max:
        raise ValueError(f"a view of {vote_labels[0].numel()} pixels is too large for int32 pixel indices")
    level_index = torch.arange(vote_labels.shape[0], device=vote_labels.device)[:, None]
    flat_labels = vote_labels.reshape(vote_labels.shape[0], -1).long()
    # finiteness tested on the [L, K+1] table, then looked up per pixel
    voting = torch.isfinite(vote_centroids[..., 0])[level_index, flat_labels].any(dim=0).nonzero().squeeze(1)
    return voting.to(torch.int32)


def pixels_and_targets(
    pixel_index: torch.Tensor, width: int, flat_labels: torch.Tensor, centroids: torch.Tensor, scale: float
) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pixel centres [P,2] of the flat pixel indices ``pixel_index`` [P] (row * width + column), their
    2D votes per level [P,L,2] (continuous frame, scaled to the render resolution) and whether each
    level carries a vote there [P,L]. (``vote_fused.vote_losses_sampled`` does this lookup in its kernel.)

    flat_labels [L, H*W] mask labels (0 = no mask), centroids [L, K+1, 2] pixel-index centroids
    (NaN: no vote, e.g. row 0 and masks cut by the image border under ``border_masks=mask_only``).
    """
    rows = torch.div(pixel_index, width, rounding_mode="floor")
    cols = pixel_index - rows * width
    pixel_xy = (torch.stack([cols, rows], dim=-1).float() + 0.5) * scale
    pixel_labels = flat_labels[:, pixel_index].long()  # [L, P]
    level_index = torch.arange(flat_labels.shape[0], device=pixel_index.device)[:, None]
    target_xy = (centroids[level_index, pixel_labels] + 0.5) * scale  # [L, P, 2]
    # finite target <=> finite centroid: tested on the [L, K+1] table, then looked up per pixel
    valid = torch.isfinite(centroids[..., 0])[level_index, pixel_labels]
    return pixel_xy, target_xy.transpose(0, 1), valid.transpose(0, 1)
