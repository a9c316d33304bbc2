"""Where a group of Gaussians sits in each training view: the mask (if any) that holds most of them.

The per-view mask table (views x Gaussians: the mask id each Gaussian is seen in, 0 = in no mask, -1 =
not seen) is read by both the training-mask check (:mod:`votesplat_ns.core.mask_consensus`) and the
whole-object rules (:mod:`votesplat_ns.core.whole_objects`); this is the one reading they share.
"""

from __future__ import annotations

import numpy as np

# A group sits in a mask when at least half of its seen members lie in it, counted only in views
# that see at least 5 of them (fewer are too few to call a majority).
DEFAULT_MIN_SHARE = 0.5
DEFAULT_MIN_SEEN = 5


def sitting_masks(
    table: np.ndarray, members: np.ndarray, min_share: float = DEFAULT_MIN_SHARE, min_seen: int = DEFAULT_MIN_SEEN
) -> np.ndarray:
    """Per view [V]: the mask (>= 1) holding at least ``min_share`` of the seen ``members``; 0 when
    that share of them is in no mask; -1 when too few are seen or no mask has the majority."""
    out = np.full(table.shape[0], -1, dtype=np.int64)
    sub = table[:, members]
    for v in range(table.shape[0]):
        values = sub[v][sub[v] >= 0]
        if values.size < min_seen:
            continue
        counts = np.bincount(values)
        best = int(counts[1:].argmax()) + 1 if counts.size > 1 else 0
        if best and counts[best] >= min_share * values.size:
            out[v] = best
        elif counts[0] >= min_share * values.size:
            out[v] = 0
    return out
