"""Instances checked against the training masks (after the vote clustering of paper §3.4).

The vote clustering sees only where the votes landed. Two failures come from that alone:

* an object whose votes did not converge to one point (large, flat, seen from one side) is cut
  into several clusters, although every training mask that covers one piece covers the others;
* an object resting in or on another (fruit in a bowl, a box on a box) can vote for nearly the
  same centre as its support, so both end in one cluster, although the masks keep them apart in
  every view.

Both are visible in the masks the votes were trained on, and so are stray clusters of background
Gaussians (floaters) that the vote support let through. Three steps, per mask level, on a table
of what each Gaussian looks like in the training views:

* **Seen.** In a view, a Gaussian is *seen* when its centre projects into the image on a pixel
  the render covers, not deeper than ``depth_tolerance`` (relative) behind the rendered depth
  there; it then lies in that pixel's mask, or in none (0). A group of Gaussians *sits in* a mask
  in a view when at least ``min_seen`` of them are seen and ``min_share`` of those lie in it
  (or in no mask: it sits in none).
* **Split.** A Gaussian of a cluster is *deviant* when, over the (at least ``min_views``) views
  where both are decided, it mostly lies in another mask than the one its cluster sits in.
  Deviants close to each other (3x the foreground's typical spacing, as the noise fill) become a
  new cluster when there are at least ``min_size`` of them; fewer stay where they were. The
  members of a split cluster that no view decided (hidden inside an object) then join the
  nearest decided member, so a split-off object takes its hidden side along (``grow``).
* **Bisect.** A cluster that holds two objects of about one size defeats the split: the mask it
  sits in is one object's in some views and the other's in the rest, so neither object's members
  are deviant in most of their views. Such a cluster is cut in two from a view where two masks each
  hold ``min_size`` of its seen members, each member joining the side whose mask it lies in in more
  of the views that tell the sides apart, until no member moves; the cut is kept when the sides sit
  in different masks in most views, as the merge asks (``bisect``), and the sides are cut again.
* **Merge.** Two clusters *agree* in a view when both sit in the same mask and disagree when both
  sit in different masks. The pair with the highest agreement / (agreement + disagreement), over
  at least ``min_views`` such views, merges while that ratio is at least ``min_agreement``; a
  merged cluster's mask is recomputed from all its Gaussians.
* **Drop.** A cluster that sits in no mask in most of the views where it is decided becomes -1.
* **Whole objects.** Then (``objects``) fragments join the instance whose masks they lie in, or
  that holds the masks they lie in when they are never most of one, floaters become background, single Gaussians settle in the touching instance whose masks hold them,
  hidden Gaussians join the object they lie inside, and those an instance holds move to the one whose hull they
  lie inside
  (:mod:`votesplat_ns.core.whole_objects`, which also gives each instance a confidence).

The thresholds are ratios, counts of views and the scene's own spacing, so they mean the same in
any scene. A cluster never seen in a training view is left as it is. Pure numpy/torch: the caller
passes the views, the training masks and a rasteriser (gsplat's ``rasterization`` signature).
"""

from __future__ import annotations

from typing import Any, Callable, Dict, Optional, Sequence, Tuple

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  (compiled, no stubs)

from votesplat_ns.core.cameras import PinholeView
from votesplat_ns.core.clustering import DEFAULT_FILL_RADIUS_FACTOR, relabel_by_size, typical_spacing
from votesplat_ns.core.mask_sightings import DEFAULT_MIN_SEEN, DEFAULT_MIN_SHARE, sitting_masks
from votesplat_ns.core.vote_render import project_to_pixels
from votesplat_ns.core.whole_objects import whole_objects

# Chosen on the tuning scenes (BENCHMARKS.md, "Training-mask check"): 2 views of evidence gave the
# best instance mIoU with GT and noisy masks; 0.7 agreement instead of 0.5 changed nothing there.
# Split groups from 5 Gaussians (was 10, HDBSCAN's own floor): small objects in containers (fruit in
# a bowl) vote where their container does and have few Gaussians; over 16 tuning-scene trainings
# (tuning and tuning-extra) 5 raised the mean instance mIoU by 0.004-0.008, the worst scene by 0.04,
# and made no scene worse by more than 0.004 (BENCHMARKS.md, "Training-mask check").
DEFAULT_MIN_AGREEMENT = 0.5
DEFAULT_MIN_VIEWS = 2
DEFAULT_MIN_SPLIT_SIZE = 5
# A split cluster hands its undecided members to the nearest decided ones: on the tuning scenes
# instance mIoU 0.885 -> 0.887 (GT) / 0.904 -> 0.905 (noisy), part 0.816 -> 0.822 / 0.759 -> 0.766,
# no scene worse by more than 0.001 (BENCHMARKS.md "Training-mask check").
DEFAULT_GROW = True
# Bisect clusters that hold two objects of about one size: on the tuning scenes (replays of 11 trainings, GT and
# SAM-like masks) it separates two boxes that SAM-like masks left as one instance on 1006 (list precision 0.556 ->
# 0.875, ghost 13.7 -> 8.8%) and raises part AP@50 on 5 of 11 runs, lowering it on none; new tuning trainings with
# SAM-like masks: part mIoU 0.680 -> 0.808, instance level unchanged (BENCHMARKS.md "Instances a user gets").
DEFAULT_BISECT = True
# relative depth behind the rendered surface that still counts as on it (tuning scene 1006's
# training views: 83-98% of an object's centres in its unoccluded views; 2%: 49-86%)
DEFAULT_DEPTH_TOLERANCE = 0.05
# blending weight (in pixels) a Gaussian needs in a view to be decided there
DEFAULT_MIN_WEIGHT = 0.5


def _view_matrices(view: PinholeView, like: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """``view``'s world-to-camera [4, 4] and intrinsics [3, 3] on ``like``'s device and dtype."""
    return view.viewmat.to(device=like.device, dtype=like.dtype), view.K.to(device=like.device, dtype=like.dtype)


def _render(
    rasterize_fn: Callable[..., tuple], gaussians: Sequence[torch.Tensor], colours: torch.Tensor, view: PinholeView
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Render [H, W, D] and alpha [H, W] of one view of ``gaussians`` (means, quats, scales linear, opacities in
    [0, 1]) with per-Gaussian ``colours`` [N, D]."""
    means, quats, scales, opacities = gaussians
    viewmat, K = _view_matrices(view, means)
    rendered, alpha, _ = rasterize_fn(
        means,
        quats,
        scales,
        opacities.reshape(-1),
        colours,
        viewmat[None],
        K[None],
        view.width,
        view.height,
        sh_degree=None,
    )
    return rendered[0], alpha[0, ..., 0]


def seen_pixels(
    rasterize_fn: Callable[..., tuple],
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    view: PinholeView,
    depth_tolerance: float = DEFAULT_DEPTH_TOLERANCE,
    min_alpha: float = 0.5,
) -> np.ndarray:
    """Flat pixel index [N] where each Gaussian's centre is seen in ``view``, -1 where it is not.

    Seen: the centre projects inside the image, in front of the camera, on a pixel the render
    covers (alpha >= ``min_alpha``) and not behind the rendered (expected) depth there by more than
    ``depth_tolerance`` of that depth. scales linear, opacities in [0, 1] ([N] or [N, 1]).
    """
    viewmat, K = _view_matrices(view, means)
    z = means @ viewmat[2, :3] + viewmat[2, 3]
    with torch.no_grad():
        rendered, alpha = _render(rasterize_fn, (means, quats, scales, opacities), z[:, None], view)
    depth = rendered[..., 0] / alpha.clamp_min(1e-6)
    u, v = torch.floor(project_to_pixels(means, viewmat, K, near_plane=1e-6)).long().unbind(-1)
    inside = (z > 1e-6) & (u >= 0) & (u < view.width) & (v >= 0) & (v < view.height)
    flat = torch.where(inside, v * view.width + u, torch.zeros_like(u))
    surface = depth.reshape(-1)[flat]
    covered = alpha.reshape(-1)[flat] >= min_alpha
    seen = inside & covered & torch.isfinite(z) & (z <= surface * (1.0 + depth_tolerance))
    return torch.where(seen, flat, torch.full_like(flat, -1)).cpu().numpy()


def drawn_masks(
    rasterize_fn: Callable[..., tuple],
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    view: PinholeView,
    labels: np.ndarray,
    min_weight: float = DEFAULT_MIN_WEIGHT,
    min_share: float = DEFAULT_MIN_SHARE,
    chunk: int = 32,
) -> np.ndarray:
    """[N] int32: the mask each Gaussian is drawn into in ``view`` (0: no mask), -1 when it is not
    decided there.

    A Gaussian's blending weight in a pixel is its share of the composite (alpha times
    transmittance, as in the colour of paper §3.1); summed over the pixels of each mask of
    ``labels`` [H, W] (0 = no mask) it says where the Gaussian is seen. Decided: its total weight is
    at least ``min_weight`` pixels and one mask (or none) holds ``min_share`` of it. Unlike the
    centre's pixel (:func:`seen_pixels`) this needs no depth tolerance, so a Gaussian behind a
    nearby surface (fruit behind a bowl's rim) counts as hidden instead of as the surface's.
    The per-mask sums are the gradient of sum_p [label(p) = k] C_k(p) with respect to a Gaussian's
    colour channel k (the composite is linear in the colours), ``chunk`` masks per render.
    """
    device = means.device
    gaussians = (means.detach(), quats.detach(), scales.detach(), opacities.detach())
    flat = torch.as_tensor(np.asarray(labels, dtype=np.int64), device=device)
    ids = torch.unique(flat)
    n = means.shape[0]
    total = torch.zeros(n, device=device, dtype=means.dtype)
    best = torch.zeros(n, device=device, dtype=means.dtype)
    best_id = torch.zeros(n, device=device, dtype=torch.int64)
    for start in range(0, int(ids.numel()), chunk):
        part = ids[start : start + chunk]
        colours = torch.zeros(n, int(part.numel()), device=device, dtype=means.dtype, requires_grad=True)
        with torch.enable_grad():
            rendered, _ = _render(rasterize_fn, gaussians, colours, view)
            target = (flat[..., None] == part).to(rendered.dtype)
            (weights,) = torch.autograd.grad((rendered * target).sum(), colours)
        total += weights.sum(dim=1)
        top, arg = weights.max(dim=1)
        better = top > best
        best = torch.where(better, top, best)
        best_id = torch.where(better, part[arg], best_id)
    decided = (total >= min_weight) & (best >= min_share * total)
    return torch.where(decided, best_id, torch.full_like(best_id, -1)).to(torch.int32).cpu().numpy()


def seen_mask_table(pixels_per_view: Sequence[np.ndarray], masks_per_view: Sequence[np.ndarray]) -> np.ndarray:
    """[V, N] int32: the mask id under each Gaussian's centre per view (0: seen, in no mask;
    -1: not seen), from :func:`seen_pixels` of each view and that view's mask labels [H, W]
    (0 = no mask) at the view's render size."""
    table = np.full((len(masks_per_view), len(pixels_per_view[0]) if pixels_per_view else 0), -1, dtype=np.int32)
    for v, (pixels, masks) in enumerate(zip(pixels_per_view, masks_per_view)):
        fill_seen_masks(table[v], pixels, masks)
    return table


def fill_seen_masks(
    row: np.ndarray, pixels: np.ndarray, masks: np.ndarray, columns: Optional[np.ndarray] = None
) -> None:
    """One view's row of a :func:`seen_mask_table`, filled in place: where ``pixels`` (:func:`seen_pixels`, of
    the Gaussians ``columns`` of the row, default all) is a pixel, the mask id of ``masks`` [H, W] there."""
    seen = pixels >= 0
    target = np.flatnonzero(seen) if columns is None else columns[seen]
    row[target] = np.asarray(masks).reshape(-1)[pixels[seen]]


def _components(points: np.ndarray, radius: float) -> np.ndarray:
    """Connected components of points closer than ``radius`` (label per point)."""
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points), len(points)))
    return connected_components(graph, directed=False)[1]


def _nearest_filled(points: np.ndarray, values: np.ndarray, open_: np.ndarray) -> np.ndarray:
    """``values`` [M] with each entry where ``open_`` [M] is true taken from the nearest (in ``points`` [M, 3]) entry
    where it is false; unchanged when either set is empty."""
    if not open_.any() or open_.all():
        return values
    _, nearest = cKDTree(points[~open_]).query(points[open_])
    values = values.copy()
    values[open_] = values[~open_][nearest]
    return values


def split_deviants(
    labels: np.ndarray,
    means: np.ndarray,
    table: np.ndarray,
    radius: float,
    min_size: int,
    min_share: float = DEFAULT_MIN_SHARE,
    min_seen: int = DEFAULT_MIN_SEEN,
    min_views: int = DEFAULT_MIN_VIEWS,
    grow: bool = DEFAULT_GROW,
) -> np.ndarray:
    """Labels with each cluster's *deviant* Gaussians moved to new clusters: those that, in most
    views where both are decided, lie in another mask than the one their cluster sits in. Deviants
    are grouped by spatial proximity (``radius``); groups smaller than ``min_size`` stay.

    With ``grow``, a cluster that was split also hands out the members that no view decided
    (hidden inside the object, or seen in fewer than ``min_views`` views): each joins the nearest
    (in space) of the members that were decided, the new groups or those confirmed in the cluster's
    own mask. Without it they stay with the cluster, so the hidden part of a split-off object
    keeps the object it was merged with."""
    out = labels.copy()
    next_label = int(labels.max()) + 1
    for label in np.unique(labels[labels >= 0]):
        members = np.flatnonzero(labels == label)
        sub = table[:, members]
        home = sitting_masks(sub, np.arange(members.size), min_share, min_seen)  # from the cluster's columns
        decided = (home[:, None] >= 1) & (sub >= 1)
        away = (decided & (sub != home[:, None])).sum(axis=0)
        views = decided.sum(axis=0)
        deviant = (views >= min_views) & (away > 0.5 * views)
        if deviant.sum() < min_size:
            continue
        idx = members[deviant]
        parts = _components(means[idx], radius)
        moved = np.zeros(members.size, dtype=bool)
        for part in np.unique(parts):
            chosen = idx[parts == part]
            if chosen.size >= min_size:
                out[chosen] = next_label
                next_label += 1
                moved[np.isin(members, chosen)] = True
        if grow and moved.any():
            confirmed = (views >= min_views) & ~deviant
            out[members] = _nearest_filled(means[members], out[members], ~(moved | confirmed))
    return out


def _two_sides(sub: np.ndarray, side: np.ndarray, min_share: float, min_seen: int, rounds: int) -> np.ndarray:
    """Members' sides [M] (0, 1; -1 undecided) re-decided until stable: each goes to the side whose mask it lies in
    in more of the views that tell the two sides apart (both sides sit in a mask there, not the same); -1 where no
    view tells. ``sub`` is the cluster's columns of the table, ``table[:, members]``."""
    for _ in range(rounds):
        # the sides' masks read from the cluster's columns, not the whole table: the same counts, 2-2.5x faster on
        # a 5M-Gaussian table (its rows are megabytes; the cluster's are its members)
        homes = [sitting_masks(sub, np.flatnonzero(side == s), min_share, min_seen) for s in (0, 1)]
        telling = (homes[0] >= 1) & (homes[1] >= 1) & (homes[0] != homes[1])
        votes = [((sub == home[:, None]) & telling[:, None]).sum(axis=0) for home in homes]
        new = np.where(votes[0] > votes[1], 0, np.where(votes[1] > votes[0], 1, -1))
        if np.array_equal(new, side) or (new == 0).sum() == 0 or (new == 1).sum() == 0:
            break
        side = new
    return side


def bisect_by_masks(
    labels: np.ndarray,
    means: np.ndarray,
    table: np.ndarray,
    min_size: int,
    min_agreement: float = DEFAULT_MIN_AGREEMENT,
    min_share: float = DEFAULT_MIN_SHARE,
    min_seen: int = DEFAULT_MIN_SEEN,
    min_views: int = DEFAULT_MIN_VIEWS,
    seeds: int = 3,
    rounds: int = 10,
) -> np.ndarray:
    """Labels with each cluster that holds two objects of about one size cut in two, again while a part can be cut.

    :func:`split_deviants` measures members against the one mask their cluster sits in per view; when two objects
    of about one size share a cluster, that mask is one object's in some views and the other's in others, so
    neither object's members are deviant in most of their views, and the pair stays one instance (tuning scene
    1006 with SAM-like masks: two boxes of 849 and 821 Gaussians, 51 and 24 deviants). Here the cut starts from a
    view where two masks each hold at least ``min_size`` (and ``min_seen``) of the cluster's seen members (the
    ``seeds`` views with the largest second mask are tried in turn). Each member then joins the side whose mask it
    lies in in more of the views that tell the sides apart, and the sides' masks are measured again, until no
    member moves (at most ``rounds``); members that no view tells go to the nearest decided member's side. The
    cut is kept when both sides hold ``min_size`` members and they sit in one mask in fewer than
    ``min_agreement`` of the at least ``min_views`` views where both sit in a mask: what :func:`merge_agreeing`
    asks to keep two clusters apart, so a view whose mask splits one object (a mask error) starts a cut that is
    not kept. With three objects in a cluster the first cut can leave pieces of one on both sides; each piece then
    sits in that object's mask in every view, and :func:`merge_agreeing`, which follows, joins them."""
    out = labels.copy()
    next_label = int(labels.max()) + 1 if (labels >= 0).any() else 0
    queue = [int(x) for x in np.unique(labels[labels >= 0])]
    floor = max(min_size, min_seen)
    while queue:
        label = queue.pop()
        members = np.flatnonzero(out == label)
        if members.size < 2 * min_size:
            continue
        sub = table[:, members]
        candidates = []
        for v in range(sub.shape[0]):
            counts = np.bincount(sub[v][sub[v] >= 1])
            if counts.size < 3:
                continue
            top = np.argsort(-counts[1:])[:2] + 1
            if counts[top[1]] >= floor:
                candidates.append((int(counts[top[1]]), v, int(top[0]), int(top[1])))
        for _, v, a, b in sorted(candidates, reverse=True)[:seeds]:
            side = np.where(sub[v] == a, 0, np.where(sub[v] == b, 1, -1))
            side = _two_sides(sub, side, min_share, min_seen, rounds)
            side = _nearest_filled(means[members], side, side < 0)
            if min((side == 0).sum(), (side == 1).sum()) < min_size:
                continue
            home_a = sitting_masks(sub, np.flatnonzero(side == 0), min_share, min_seen)
            home_b = sitting_masks(sub, np.flatnonzero(side == 1), min_share, min_seen)
            both = (home_a >= 1) & (home_b >= 1)
            if both.sum() < min_views or (home_a[both] == home_b[both]).mean() >= min_agreement:
                continue
            out[members[side == 1]] = next_label
            queue += [label, next_label]
            next_label += 1
            break
    return out


def merge_agreeing(
    labels: np.ndarray,
    table: np.ndarray,
    min_agreement: float = DEFAULT_MIN_AGREEMENT,
    min_views: int = DEFAULT_MIN_VIEWS,
    min_share: float = DEFAULT_MIN_SHARE,
    min_seen: int = DEFAULT_MIN_SEEN,
) -> Tuple[np.ndarray, int]:
    """Greedy merge of clusters that sit in the same mask in at least ``min_agreement`` of the
    views where both sit in a mask (and there are at least ``min_views`` such views)."""
    ids = [int(x) for x in np.unique(labels[labels >= 0])]
    members = {i: np.flatnonzero(labels == i) for i in ids}
    sitting = {i: sitting_masks(table, members[i], min_share, min_seen) for i in ids}

    def agreement(a: int, b: int) -> float:
        both = (sitting[a] >= 1) & (sitting[b] >= 1)
        n = int(both.sum())
        if n < min_views:
            return -1.0
        return float((sitting[a][both] == sitting[b][both]).sum()) / n

    scores = {(a, b): agreement(a, b) for k, a in enumerate(ids) for b in ids[k + 1 :]}
    merges = 0
    while scores:
        (a, b), best = max(scores.items(), key=lambda item: item[1])
        if best < min_agreement:
            break
        members[a] = np.concatenate([members[a], members.pop(b)])
        sitting[a] = sitting_masks(table, members[a], min_share, min_seen)
        del sitting[b]
        ids.remove(b)
        scores = {pair: s for pair, s in scores.items() if a not in pair and b not in pair}
        for c in ids:
            if c != a:
                scores[(min(a, c), max(a, c))] = agreement(min(a, c), max(a, c))
        merges += 1
    out = np.full(labels.shape, -1, dtype=np.int64)
    for i, idx in members.items():
        out[idx] = i
    return out, merges


def drop_unmasked(
    labels: np.ndarray, table: np.ndarray, min_share: float = DEFAULT_MIN_SHARE, min_seen: int = DEFAULT_MIN_SEEN
) -> np.ndarray:
    """Clusters that sit in no mask in most of the views where they are decided become -1
    (background that the vote support let through: floaters, backdrop bits)."""
    out = labels.copy()
    for label in np.unique(labels[labels >= 0]):
        members = np.flatnonzero(labels == label)
        home = sitting_masks(table, members, min_share, min_seen)
        decided = home >= 0
        if decided.sum() >= 1 and (home[decided] == 0).sum() > 0.5 * decided.sum():
            out[members] = -1
    return out


def regroup_with_masks(
    labels: np.ndarray,
    means: np.ndarray,
    table: np.ndarray,
    split: bool = True,
    merge: bool = True,
    drop: bool = True,
    min_agreement: float = DEFAULT_MIN_AGREEMENT,
    min_views: int = DEFAULT_MIN_VIEWS,
    min_share: float = DEFAULT_MIN_SHARE,
    min_seen: int = DEFAULT_MIN_SEEN,
    min_size: int = DEFAULT_MIN_SPLIT_SIZE,
    grow: bool = DEFAULT_GROW,
    bisect: bool = DEFAULT_BISECT,
    objects: bool = True,
    votes: Optional[np.ndarray] = None,
    **object_options: Any,
) -> Tuple[np.ndarray, Dict[str, Any]]:
    """One level's instance labels [N] (-1: noise/background) checked against its training masks
    (``table`` [V, N] from :func:`seen_mask_table`): split deviants, merge agreeing clusters, drop
    clusters that sit in no mask; renumbered by decreasing size. See the module docstring. ``bisect`` cuts
    clusters that hold two objects of about one size (:func:`bisect_by_masks`) after the split.

    With ``objects``, the whole-object rules of :func:`votesplat_ns.core.whole_objects.whole_objects`
    follow (fragments join, floaters drop, Gaussians settle in the instance whose masks hold them, hidden
    Gaussians join; ``object_options`` are its keywords: ``join``, ``orphans``, ``floaters``, ``settle``,
    ``hidden``, ``rehome``, ``join_ratio``, ...; ``votes`` [N, 3], NaN where a Gaussian has none, for
    ``join_vote_factor``); their counts go under
    ``stats["objects"]`` and the instances' confidence [K] under ``stats["confidence"]`` (an array,
    which :func:`votesplat_ns.core.clustering.cluster_levels` moves to the level)."""
    labels = np.asarray(labels, dtype=np.int64)
    stats: Dict[str, Any] = {"num_clusters_before": int(labels.max()) + 1 if (labels >= 0).any() else 0}
    if table.shape[0] == 0 or not (labels >= 0).any():
        return labels.copy(), stats
    foreground = np.flatnonzero(labels >= 0)
    spacing = typical_spacing(means[foreground])
    radius = DEFAULT_FILL_RADIUS_FACTOR * spacing
    out = labels
    if split:
        out = split_deviants(out, means, table, radius, min_size, min_share, min_seen, min_views, grow)
        stats["num_after_split"] = int(np.unique(out[out >= 0]).size)
    if bisect:
        out = bisect_by_masks(out, means, table, min_size, min_agreement, min_share, min_seen, min_views)
        stats["num_after_bisect"] = int(np.unique(out[out >= 0]).size)
    if merge:
        out, stats["merges"] = merge_agreeing(out, table, min_agreement, min_views, min_share, min_seen)
    if drop:
        out = drop_unmasked(out, table, min_share, min_seen)
    out = relabel_by_size(out)
    stats["num_clusters"] = int(out.max()) + 1 if (out >= 0).any() else 0
    if objects:
        out, stats["confidence"], stats["objects"] = whole_objects(
            out,
            means,
            table,
            spacing,
            min_views=min_views,
            min_share=min_share,
            min_seen=min_seen,
            votes=votes,
            **object_options,
        )
        stats["num_clusters"] = int(out.max()) + 1 if (out >= 0).any() else 0
    return out, stats
