"""Whole objects: fragments, floaters and hidden Gaussians, after the training-mask check (paper §3.4).

The vote clustering and the mask check (:mod:`votesplat_ns.core.mask_consensus`) leave three kinds
of error that a user sees in the instance list and in an object's removal:

* **fragments**: small clusters of an object's Gaussians whose votes did not reach the object's
  centre. The check's merge decides per cluster and view (at least ``min_seen`` members seen), so a
  fragment that few views see well never merges;
* **floaters**: clusters of background Gaussians that the vote support let through;
* **hidden Gaussians**: Gaussians behind an object's front surface in every training view never
  vote (vote support 0), so they stay background, and a removed object leaves them behind.

Eight rules, each switchable (keywords of :func:`whole_objects`, passed on by
:func:`~votesplat_ns.core.mask_consensus.regroup_with_masks`, so ``mc.<key>`` in
``benchmarks/sweep.py`` reaches them). The evidence is the check's per-view mask table [V, N]
(-1: not seen, 0: seen in no mask, k >= 1: seen in mask k), read per member Gaussian instead of per
cluster, so a fragment seen by one or two of its Gaussians per view still has a say:

* **Join** (``join``): an instance of at most ``join_ratio`` times another's size joins it when it
  touches it (some member within ``contact_factor`` typical spacings of the other's Gaussians) and
  its members, in the views where the larger one sits in a mask, lie in that same mask in at least
  ``join_agreement`` of their sightings, over at least ``min_views`` views. Contact alone never
  joins (stacked cubes touch; their masks differ), and a small object in or on a larger one (fruit
  in a bowl, a box on a table) is seen in its own masks, so it stays apart. Among several
  candidates the one with the highest agreement wins; smaller instances are decided first. With
  ``join_vote_factor`` (off by default) the fragment's median vote must also lie within that many
  of the larger one's vote spreads of its median vote: a fragment exists because its votes missed
  the object's centre, so vote proximity is weak evidence, kept as a variant to measure.
* **Orphans** (``orphans``): an instance of at most ``join_ratio`` times another's size that makes up at least
  ``min_share`` of the mask it sits in in fewer than ``min_views`` views (SAM never showed it on its own) joins the
  instance it touches that holds at least ``min_share`` of those masks in the most views (at least ``min_views``),
  counting a view only when the mask also holds ``orphan_cover`` of the Gaussians of that instance the view sees
  (a piece of it, not a small mask on it through which a few of its Gaussians just behind show).
  Noise in the masks splits an object's mask in two: a fragment whose Gaussians lie in the half that its host sits
  in less often then fails the join rule's agreement, yet every mask it lies in is mostly its host's. A real
  object, however small, is the larger part of its own mask in the views that show it (on dumped runs of the scene
  family every object's instance is, in at least two views; the fragments left, in none). It reads no votes.
* **Floaters** (``floaters``): an instance whose sightings lie in no mask in most views with
  evidence (at least ``min_views``) becomes background. So does one that fewer than ``min_views``
  views see (``unseen``): a cluster hidden inside or behind an object in every view, whose
  Gaussians voted during training. On the tuning scenes these were most of the instances left
  over (12 of 20 on one scene), each a few dozen to a few hundred Gaussians that a user could
  only find in the list. A view sees an instance when it sees at least ``min_seen`` of its
  members (all of them, if it has fewer; ``unseen_min_seen``), the evidence the merge and the
  confidence ask of a view: a cluster of hundreds of which two or three views glimpse a Gaussian
  or two is not shown by any view (on the tuning scenes, the instances left unmatched that way
  sat behind objects' edges, 95-305 Gaussians with 2-26 sightings in all). The hidden rule below
  then gives its Gaussians to the object they lie inside, so a removal still takes them. With
  ``unseen=False`` only an unseen instance that touches no other becomes background (contact is
  its only evidence otherwise).
* **Settle** (``settle``): a Gaussian (of an instance, or background) moves to an instance it touches (within
  ``contact_factor`` typical spacings of its Gaussians) when, in the views that tell the two apart (the instance
  sits in a mask there, and not in the mask the Gaussian's own instance sits in; background sits in none), it
  lies in that instance's mask in at least ``settle_agreement`` of its sightings, over at least ``min_views``
  views. The vote clustering cuts touching objects along the votes and leaves an object's fringe out, so some of
  an object's Gaussians sit in a neighbour's instance or in the background although the training masks show them
  on the object; a removal of the object leaves them behind. Each Gaussian is decided on its own, against the
  instances as the rules before left them (among several instances the one with the highest share wins); never an
  instance's majority, since whole instances are the join rule's to move, and never from an instance into one of
  at most ``join_ratio`` its size: the contact of a small object with its container, which the masks split about
  evenly, is the contact rule's, which runs after it.
* **Contact** (``contact``): a Gaussian of one instance that lies in the box (grown by ``hidden_reach``
  typical spacings) of an instance of at most ``join_ratio`` times its size moves to the smaller one when,
  over at least ``min_views`` views, it lies in the smaller one's mask in at least ``contact_ratio`` times
  as many views as in its own instance's mask (views where both sit in one mask do not count). This is a
  small object's contact with its container (a lime in a bowl, a box on a table): the vote clustering cuts
  the two along the votes, the Gaussians where they touch go to the larger one, and a removal of the small
  object leaves them behind as a ghost. The training masks see them in the small object's mask about as
  often as in the container's, since the centre test's depth tolerance accepts both surfaces at the
  contact. Each Gaussian is decided on its own, against the instances as the rules before left them. Two
  touching objects of similar size (stacked cubes) are neither's container.
* **Hidden** (``hidden``): a Gaussian left as background that no view sees in no mask (never seen,
  or seen in a mask) takes instance j when most of its ``hidden_neighbours`` nearest *settled*
  Gaussians (in an instance, or background that a view saw outside every mask) are of j, it lies
  inside j's convex hull at least ``hidden_margin`` typical spacings in from the hull's faces (only
  inside it, when a view sees it in j's mask), and in the views that see it in a mask it lies in
  j's mask at least half the time. The hull keeps the
  table under an object out (it lies on or below the hull's bottom face); the settled background
  neighbours keep a Gaussian of the floor between two objects out. Outside the hull, one that no
  view sees at all still takes j when *all* its settled neighbours are of j and it lies within
  ``hidden_reach`` typical spacings of j's Gaussians and farther than the contact distance from any
  background a view saw: the hull of the visible members misses the fuzz just off an object's
  surface, which a removal would leave behind; the table hidden under an object continues the table
  seen around it, so it stays out. With ``reach_in_masks``, one that views see in j's mask (at least
  half of its sightings in a mask, as the hull asks of a seen one) takes j within the same reach on
  the majority of its settled neighbours, near seen background or not: the masks place it, and it is
  the fringe of an object that the vote clustering left out.
* **Rehome** (``rehome``): a Gaussian of an instance that no training view sees (hidden behind surfaces in every
  view) has no mask evidence; the vote clustering placed it by its votes alone, which, where two objects touch,
  mix both. It moves to another instance when it lies inside the convex hull of that instance's seen Gaussians by
  at least ``hidden_margin`` typical spacings, inside no other hull by that much, and not inside the hull of its own
  instance's seen Gaussians at all. A removal of the object would otherwise leave it behind, and the viewer would
  show it in the neighbour. Never from a small object into one over 1 / ``join_ratio`` times its size: a small
  object's hidden side (a fruit's underside in a bowl) lies inside its container's hull and outside the hull of its
  own seen Gaussians.
* **Confidence** (always computed): per instance, the share of its sightings (views where it sits in
  a mask) that lie in its mask, times n / (n + ``min_views``) for its n views of evidence. A
  fragment or a cluster cut across masks sits in its mask in few views or with a low share, so it
  ranks below whole objects (3D AP, issue 34); the view term discounts an agreement measured in one
  or two views, where a single view makes it 0 or 1. HDBSCAN's cluster stability is not used: the
  mask check splits and merges clusters, after which it no longer describes the instance.

Distances are typical spacings of the foreground (:func:`~votesplat_ns.core.clustering.typical_spacing`),
sizes are ratios, evidence is shares of sightings and counts of views: the same in any scene.
"""

from __future__ import annotations

from typing import Any, Dict, Optional, Tuple

import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree  # pyright: ignore[reportAttributeAccessIssue]  (compiled, no stubs)

from votesplat_ns.core.mask_sightings import sitting_masks

# A fragment is at most a quarter of the instance it joins: the fragments left on the family scenes
# are 5-510 Gaussians beside objects of thousands, while two touching objects of similar size
# (stacked cubes) are never candidates whatever their masks say. Small objects are kept apart by
# their masks, not by this ratio (fruit of 19-84 Gaussians is far below it).
DEFAULT_JOIN_RATIO = 0.25
# Share of a fragment's sightings in the larger instance's mask. Above the merge's 0.5 because one
# Gaussian's sighting is noisier than a cluster's majority (the centre test's depth tolerance lets a
# Gaussian just behind an edge count as seen in the mask in front).
DEFAULT_JOIN_AGREEMENT = 0.6
# Contact: within the noise fill's radius (3 typical spacings), the scale at which the vote
# clustering already treats Gaussians as neighbours.
DEFAULT_CONTACT_FACTOR = 3.0
DEFAULT_HIDDEN_NEIGHBOURS = 8
# Inside the hull by half a typical spacing: the table's Gaussians under an object lie on the plane
# of the hull's bottom face (the lowest visible Gaussians of the object touch the table).
DEFAULT_HIDDEN_MARGIN = 0.5
# Outside the hull, a Gaussian no view saw joins an instance when all its settled neighbours are of it and it
# lies within this many typical spacings of it, clear of seen background: the hull of the visible members
# misses the fuzz just off an object's surface, which a removal leaves behind (BENCHMARKS.md "Instances a
# user gets"). On the tuning scenes the Gaussians it takes lie 1-4 GT surface tolerances off an object.
DEFAULT_HIDDEN_REACH = 1.5
# With the contact rule on, a Gaussian at a small object's contact with its container moves to the small object
# when it lies in the small object's mask in at least half as many views as in its own instance's (BENCHMARKS.md
# "Instances a user gets": chosen on the tuning scenes against 0.75 and 1).
DEFAULT_CONTACT_RATIO = 0.5
# Settle: a Gaussian moves to a touching instance whose masks hold it in this share of the views that tell the two
# apart: the share the join rule asks of a fragment's sightings, not tuned apart (BENCHMARKS.md "Instances a user
# gets" chose the rule on the tuning scenes).
DEFAULT_SETTLE_AGREEMENT = DEFAULT_JOIN_AGREEMENT
# Rehome never-seen Gaussians into the one instance whose hull holds them: on the tuning scenes (18 trainings, GT and
# SAM-like masks) the instance ghost fell 2.47 -> 2.32% (GT) and 4.65 -> 4.61% (noisy), the part ghost 5.09 -> 4.87%
# and 9.37 -> 9.17%, mIoU unchanged; the largest rise was 0.2 points (BENCHMARKS.md "Instances a user gets").
DEFAULT_REHOME = True
# Orphans join the instance that holds their masks: on the tuning scenes (24 trainings, GT and SAM-like masks) it
# changed 6 of 48 run-levels, each to fewer instances and a higher list precision, the ghost lower or equal
# (BENCHMARKS.md "Instances a user gets").
DEFAULT_ORPHANS = True
# A mask counts as the host's for an orphan only when it holds at least this share of the host's Gaussians that the
# view sees: the masks of the fragments adopted on the dumped runs hold 25-100% of their host in at least three views
# each, while the mask of a small object resting on a larger one holds a few of the larger one's Gaussians just behind
# it, which the centre test's depth tolerance lets through (0.3-0.4% for a fruit's visible top on its bowl).
DEFAULT_ORPHAN_COVER = 0.1
# Candidates of the settle rule whose sightings are compared at once (their [V, C] slices of the table).
SETTLE_CHUNK = 1 << 16


def _sightings(table: np.ndarray, members: np.ndarray, home: np.ndarray) -> Tuple[int, int, int]:
    """(agree, against, views): members' sightings in views where ``home`` (per view, the mask an
    instance sits in) is a mask: seen in that mask, seen elsewhere (another mask or none), and the
    number of views with at least one such sighting."""
    rows = np.flatnonzero(home >= 1)
    if rows.size == 0 or members.size == 0:
        return 0, 0, 0
    sub = table[np.ix_(rows, members)]
    seen = sub >= 0
    agree = sub == home[rows, None]
    return int(agree.sum()), int((seen & ~agree).sum()), int(seen.any(axis=1).sum())


def instance_confidence(
    labels: np.ndarray, table: np.ndarray, min_views: int, min_share: float, min_seen: int
) -> np.ndarray:
    """[K] confidence of instances 0..K-1 of ``labels`` (module docstring, "Confidence")."""

    k = int(labels.max()) + 1 if (labels >= 0).any() else 0
    out = np.zeros(k, dtype=np.float64)
    for label in range(k):
        members = np.flatnonzero(labels == label)
        home = sitting_masks(table, members, min_share, min_seen)
        agree, against, _ = _sightings(table, members, home)
        views = int((home >= 1).sum())
        if agree + against:
            out[label] = agree / (agree + against) * views / (views + max(min_views, 1))
    return out


def _touching(means: np.ndarray, labels: np.ndarray, members: np.ndarray, radius: float, tree, index) -> np.ndarray:
    """Labels of other instances with a Gaussian within ``radius`` of one of ``members``."""
    hits = tree.query_ball_point(means[members], radius)
    near = np.unique(np.concatenate([index[np.asarray(h, dtype=np.int64)] for h in hits])) if len(hits) else []
    found = np.unique(labels[np.asarray(near, dtype=np.int64)])
    own = labels[members[0]]
    return found[(found >= 0) & (found != own)]


def _votes_close(votes, members: np.ndarray, host: np.ndarray, factor) -> bool:
    """Whether the median vote of ``members`` lies within ``factor`` times the host's vote spread
    (median distance of its votes to their median) of the host's median vote; True when either
    has no finite vote (no evidence either way)."""
    own, theirs = votes[members], votes[host]
    own, theirs = own[np.isfinite(own).all(axis=1)], theirs[np.isfinite(theirs).all(axis=1)]
    if own.shape[0] == 0 or theirs.shape[0] == 0:
        return True
    centre = np.median(theirs, axis=0)
    spread = float(np.median(np.linalg.norm(theirs - centre, axis=1)))
    return float(np.linalg.norm(np.median(own, axis=0) - centre)) <= factor * max(spread, 1e-12)


def join_fragments(
    labels: np.ndarray,
    means: np.ndarray,
    table: np.ndarray,
    spacing: float,
    join_ratio: float = DEFAULT_JOIN_RATIO,
    join_agreement: float = DEFAULT_JOIN_AGREEMENT,
    contact_factor: float = DEFAULT_CONTACT_FACTOR,
    min_views: int = 2,
    min_share: float = 0.5,
    min_seen: int = 5,
    votes: Optional[np.ndarray] = None,
    join_vote_factor: Optional[float] = None,
) -> Tuple[np.ndarray, Dict[str, int]]:
    """Labels after the join rule (module docstring); stats: fragments joined, Gaussians moved,
    touching candidates refused by their masks, and (with ``votes`` [N, 3], NaN where a Gaussian
    has none, and ``join_vote_factor``) candidates refused by their votes."""

    out = labels.copy()
    stats = {"joined": 0, "joined_gaussians": 0, "refused_by_masks": 0, "refused_by_votes": 0}
    use_votes = votes is not None and join_vote_factor is not None
    ids, sizes = np.unique(out[out >= 0], return_counts=True)
    if ids.size < 2 or spacing <= 0:
        return out, stats
    labelled = np.flatnonzero(out >= 0)
    tree = cKDTree(means[labelled])
    homes = {int(i): sitting_masks(table, np.flatnonzero(out == i), min_share, min_seen) for i in ids}
    size = {int(i): int(s) for i, s in zip(ids, sizes)}
    for label in [int(i) for i in ids[np.argsort(sizes, kind="stable")]]:
        members = np.flatnonzero(out == label)
        # only a fragment of some larger instance looks for contact (the query is per member)
        if members.size == 0 or members.size > join_ratio * max(size.values()):
            continue
        touching = _touching(means, out, members, contact_factor * spacing, tree, labelled)
        best, best_share = -1, -1.0
        for other in (int(t) for t in touching):
            if members.size > join_ratio * size[other]:
                continue
            agree, against, views = _sightings(table, members, homes[other])
            share = agree / (agree + against) if agree + against else 0.0
            if views < min_views or share < join_agreement:
                stats["refused_by_masks"] += 1
            elif use_votes and not _votes_close(votes, members, np.flatnonzero(out == other), join_vote_factor):
                stats["refused_by_votes"] += 1
            elif share > best_share:
                best, best_share = other, share
        if best >= 0:
            out[members] = best
            size[best] += members.size
            size[label] = 0
            stats["joined"] += 1
            stats["joined_gaussians"] += int(members.size)
    return out, stats


def adopt_orphans(
    labels: np.ndarray,
    means: np.ndarray,
    table: np.ndarray,
    spacing: float,
    join_ratio: float = DEFAULT_JOIN_RATIO,
    contact_factor: float = DEFAULT_CONTACT_FACTOR,
    min_views: int = 2,
    min_share: float = 0.5,
    min_seen: int = 5,
    orphan_cover: float = DEFAULT_ORPHAN_COVER,
) -> Tuple[np.ndarray, Dict[str, int]]:
    """Labels after the orphans rule (module docstring); stats: instances adopted and their Gaussians. Who holds a
    mask is read once, from the labels as they come in."""
    out = labels.copy()
    stats = {"adopted": 0, "adopted_gaussians": 0}
    ids, sizes = np.unique(out[out >= 0], return_counts=True)
    if ids.size < 2 or spacing <= 0:
        return out, stats
    size = {int(i): int(s) for i, s in zip(ids, sizes)}
    candidates = [int(i) for i, s in zip(ids, sizes) if s <= join_ratio * sizes.max()]
    homes = {label: sitting_masks(table, np.flatnonzero(out == label), min_share, min_seen) for label in candidates}
    # per view, the Gaussians of each instance (column 0: background) in each mask some candidate sits in, and those
    # the view sees at all: one bincount over the view's row of the table, by table value + 1 (row 0: not seen)
    width = int(ids.max()) + 2
    held: Dict[Tuple[int, int], np.ndarray] = {}
    seen: Dict[int, np.ndarray] = {}
    for view in range(table.shape[0]):
        wanted = {int(home[view]) for home in homes.values() if home[view] >= 1}
        if not wanted:
            continue
        rows = int(table[view].max()) + 2
        keys = (table[view].astype(np.int64) + 1) * width + (out + 1)
        counts = np.bincount(keys, minlength=rows * width).reshape(rows, width)
        held.update(((view, mask), counts[mask + 1]) for mask in wanted)
        seen[view] = counts[1:].sum(axis=0)
    labelled = np.flatnonzero(out >= 0)
    tree = cKDTree(means[labelled])
    for label in sorted(candidates, key=lambda c: size[c]):
        owned, owners = 0, {}
        for view in np.flatnonzero(homes[label] >= 1):
            row = held[(int(view), int(homes[label][view]))]
            if row[label + 1] >= min_share * row.sum():
                owned += 1
                continue
            others = row[1:].copy()
            others[label] = 0
            owner = int(others.argmax())
            if others[owner] >= min_share * row.sum() and others[owner] >= orphan_cover * seen[int(view)][owner + 1]:
                owners[owner] = owners.get(owner, 0) + 1
        if owned >= min_views or not owners:
            continue
        members = np.flatnonzero(out == label)
        touching = set(int(t) for t in _touching(means, out, members, contact_factor * spacing, tree, labelled))
        hosts = [
            (views, host)
            for host, views in owners.items()
            if host in touching and views >= min_views and members.size <= join_ratio * size[host]
        ]
        if not hosts:
            continue
        _, host = max(hosts)
        out[members] = host
        size[host] += members.size
        size[label] = 0
        stats["adopted"] += 1
        stats["adopted_gaussians"] += int(members.size)
    return out, stats


def drop_floaters(
    labels: np.ndarray,
    means: np.ndarray,
    table: np.ndarray,
    spacing: float,
    contact_factor: float = DEFAULT_CONTACT_FACTOR,
    min_views: int = 2,
    unseen: bool = True,
    min_seen: int = 1,
) -> Tuple[np.ndarray, Dict[str, int]]:
    """Labels after the floater rule (module docstring); stats: instances and Gaussians dropped.
    ``min_seen``: members (all of them, if it has fewer) a view must see to count as seeing an instance."""
    out = labels.copy()
    stats = {"floaters": 0, "floater_gaussians": 0}
    labelled = np.flatnonzero(out >= 0)
    if labelled.size == 0:
        return out, stats
    tree = cKDTree(means[labelled])
    for label in np.unique(out[labelled]):
        members = np.flatnonzero(out == label)
        sub = table[:, members]
        seen_views = (sub >= 0).any(axis=1)
        outside = (sub == 0).sum(axis=1)
        inside = (sub >= 1).sum(axis=1)
        unmasked_views = int((seen_views & (outside > inside)).sum())
        # views that see enough of it to show it to a user (unseen=False: any member, the contact test decides the rest)
        need = min(max(min_seen, 1), members.size) if unseen else 1
        evidence_views = int(((sub >= 0).sum(axis=1) >= need).sum())
        if evidence_views >= min_views:
            floater = unmasked_views > 0.5 * seen_views.sum()
        elif unseen:
            floater = True
        elif not seen_views.any():
            floater = _touching(means, out, members, contact_factor * spacing, tree, labelled).size == 0
        else:
            floater = False
        if floater:
            out[members] = -1
            stats["floaters"] += 1
            stats["floater_gaussians"] += int(members.size)
    return out, stats


def _grown_box(points: np.ndarray, grow: float) -> Tuple[np.ndarray, np.ndarray]:
    """(low [3], high [3]): the bounding box of ``points`` [P, 3], grown by ``grow`` on every side."""
    return points.min(axis=0) - grow, points.max(axis=0) + grow


def _in_box(points: np.ndarray, box: Tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """[P] bool: ``points`` inside ``box`` (as :func:`_grown_box` gives it)."""
    return ((points >= box[0]) & (points <= box[1])).all(axis=1)


def take_contact(
    labels: np.ndarray,
    means: np.ndarray,
    table: np.ndarray,
    spacing: float,
    contact_ratio: float = DEFAULT_CONTACT_RATIO,
    reach: float = DEFAULT_HIDDEN_REACH,
    size_ratio: float = DEFAULT_JOIN_RATIO,
    min_views: int = 2,
    min_share: float = 0.5,
    min_seen: int = 5,
) -> Tuple[np.ndarray, Dict[str, int]]:
    """Labels after the contact rule (module docstring); stats: Gaussians moved and the instances they left."""
    out = labels.copy()
    stats = {"contact_gaussians": 0, "contact_sources": 0}
    ids = [int(i) for i in np.unique(labels) if i >= 0]
    if len(ids) < 2:
        return out, stats
    members = {i: np.flatnonzero(labels == i) for i in ids}
    homes = {i: sitting_masks(table, members[i], min_share, min_seen) for i in ids}
    boxes = {i: _grown_box(means[members[i]], reach * spacing) for i in ids}
    for large in ids:
        smaller = [i for i in ids if members[i].size <= size_ratio * members[large].size]
        if not smaller:
            continue
        points = means[members[large]]
        inside = {i: _in_box(points, boxes[i]) for i in smaller}
        candidates = np.flatnonzero(np.any(np.stack(list(inside.values())), axis=0))
        if candidates.size == 0:
            continue
        sub = table[:, members[large][candidates]]  # [V, C]: only the Gaussians in some smaller instance's box
        own_home = homes[large][:, None]
        in_own = ((sub == own_home) & (own_home > 0)).sum(axis=0)
        best, best_views = np.full(candidates.size, -1), np.zeros(candidates.size, dtype=np.int64)
        for small in smaller:
            home = homes[small][:, None]
            in_small = ((sub == home) & (home > 0) & (home != own_home)).sum(axis=0)
            take = (
                inside[small][candidates]
                & (in_small >= min_views)
                & (in_small >= contact_ratio * in_own)
                & (in_small > best_views)
            )
            best[take], best_views[take] = small, in_small[take]
        moving = best >= 0
        if moving.any():
            out[members[large][candidates[moving]]] = best[moving]
            stats["contact_gaussians"] += int(moving.sum())
            stats["contact_sources"] += 1
    return out, stats


def _inside_hull(points: np.ndarray, hull_points: np.ndarray, margin) -> np.ndarray:
    """[P] bool: ``points`` inside the convex hull of ``hull_points`` by at least ``margin`` (a
    number or one per point)."""
    return _hull_depth(points, hull_points) >= np.asarray(margin, dtype=np.float64)


def _hull_depth(points: np.ndarray, hull_points: np.ndarray) -> np.ndarray:
    """[P]: how deep ``points`` lie inside the convex hull of ``hull_points``, the distance to its nearest face
    (negative outside; -inf outside the hull's bounding box, or everywhere when the hull is flat or has fewer than
    4 points)."""
    depth = np.full(points.shape[0], -np.inf)
    if hull_points.shape[0] < 4:
        return depth
    try:
        hull = ConvexHull(hull_points)
    except QhullError:  # flat or degenerate: nothing is inside
        return depth
    # equations: unit outward normals and offsets, inside where normal . x + offset <= 0; the hull's bounding box
    # first, since the facet test is points x facets
    index = np.flatnonzero(_in_box(points, _grown_box(hull_points, 0.0)))
    for start in range(0, index.size, 65536):
        part = index[start : start + 65536]
        depth[part] = -(points[part] @ hull.equations[:, :3].T + hull.equations[:, 3]).max(axis=1)
    return depth


def _near_some_instance(points: np.ndarray, means: np.ndarray, labels: np.ndarray, grow: float) -> np.ndarray:
    """[M] bool: ``points`` inside the bounding box, grown by ``grow`` on every side, of some instance's Gaussians."""
    order = np.argsort(labels, kind="stable")
    sorted_labels = labels[order]
    starts = np.searchsorted(sorted_labels, 0)
    bounds = np.flatnonzero(np.diff(sorted_labels[starts:])) + starts + 1
    near = np.zeros(len(points), dtype=bool)
    for members in np.split(order[starts:], bounds - starts):
        open_rows = np.flatnonzero(~near)
        inside = _in_box(points[open_rows], _grown_box(means[members], grow))
        near[open_rows[inside]] = True
    return near


def take_hidden(
    labels: np.ndarray,
    means: np.ndarray,
    table: np.ndarray,
    spacing: float,
    hidden_neighbours: int = DEFAULT_HIDDEN_NEIGHBOURS,
    hidden_margin: float = DEFAULT_HIDDEN_MARGIN,
    min_share: float = 0.5,
    min_seen: int = 5,
    eligible: Optional[np.ndarray] = None,
    hidden_reach: float = DEFAULT_HIDDEN_REACH,
    contact_factor: float = DEFAULT_CONTACT_FACTOR,
    reach_in_masks: bool = True,
) -> Tuple[np.ndarray, Dict[str, int]]:
    """Labels after the hidden-Gaussian rule (module docstring); ``eligible`` [N] bool limits the
    Gaussians that may join (default: all finite ones). Stats: Gaussians taken (of them, taken outside the
    hull by ``hidden_reach``, and of those, seen in the instance's masks), and background kept because a view
    saw it outside every mask."""

    out = labels.copy()
    stats = {"hidden_taken": 0, "hidden_reached": 0, "reached_in_masks": 0, "seen_background": 0}
    finite = np.isfinite(means).all(axis=1)
    open_ = (out < 0) & finite & (eligible if eligible is not None else True)
    outside = (table == 0).sum(axis=0)
    inside = (table >= 1).sum(axis=0)
    confirmed = (out < 0) & finite & (outside > 0) & (outside >= inside)
    stats["seen_background"] = int((confirmed & open_).sum())
    candidates = np.flatnonzero(open_ & ~confirmed)
    settled = np.flatnonzero((out >= 0) | confirmed)
    if candidates.size == 0 or not (out >= 0).any() or settled.size == 0:
        return out, stats
    # a Gaussian outside every instance's box (grown by the reach) can join none: neither inside a hull nor within
    # reach; leaving it out spares the neighbour search below, which dominates on scenes of millions
    candidates = candidates[_near_some_instance(means[candidates], means, out, max(hidden_reach, 0.0) * spacing)]
    if candidates.size == 0:
        return out, stats
    k = min(hidden_neighbours, settled.size)
    _, near = cKDTree(means[settled]).query(means[candidates], k=k, workers=-1)
    background_tree = cKDTree(means[confirmed]) if confirmed.any() else None
    near_labels = out[settled[np.asarray(near).reshape(candidates.size, k)]]
    # the label held by more than half of the k neighbours (k compares of k columns, no per-label pass)
    counts = np.stack([(near_labels == near_labels[:, [j]]).sum(axis=1) for j in range(k)], axis=1)
    top = counts.argmax(axis=1)
    rows = np.arange(candidates.size)
    winner = np.where(counts[rows, top] > 0.5 * k, near_labels[rows, top], -1)
    unanimous = counts[rows, top] == k
    never_seen = (outside + inside)[candidates] == 0  # no view saw it, in a mask or outside every mask
    for label in np.unique(winner[winner >= 0]):
        picked = winner == label
        chosen = candidates[picked]
        members = np.flatnonzero(out == label)
        # in the views that see a candidate in a mask, it must lie in this instance's mask; one
        # that does (seen, never voted) needs only to be inside the hull, one that no view saw
        # needs the margin
        home = sitting_masks(table, members, min_share, min_seen)
        rows = np.flatnonzero(home >= 1)
        masked = agree = np.zeros(chosen.size, dtype=np.int64)
        if rows.size:
            sub = table[np.ix_(rows, chosen)]
            masked, agree = (sub >= 1).sum(axis=0), (sub == home[rows, None]).sum(axis=0)
        confirmed_in_mask = (masked > 0) & (agree >= 0.5 * masked)
        margin = np.where(confirmed_in_mask, 0.0, hidden_margin * spacing)
        keep = _inside_hull(means[chosen], means[members], margin) & (agree >= 0.5 * masked)
        # outside the hull, close to it (the hull of the visible members misses the fuzz just off an object's
        # surface): hidden from every view and every settled neighbour of this instance; or (reach_in_masks)
        # seen in this instance's masks, as the hull asks of one it takes that a view saw
        reach = unanimous[picked] & never_seen[picked]
        if reach_in_masks:
            reach |= confirmed_in_mask
        reach = np.flatnonzero(~keep & reach)
        if hidden_reach > 0 and reach.size:
            distance, _ = cKDTree(means[members]).query(means[chosen[reach]])
            within = reach[distance <= hidden_reach * spacing]
            # and, unseen, clear of the background that views saw: the table under an object continues the
            # table seen around it, within the contact distance at the object's foot (one seen in the masks
            # is placed by them)
            if within.size and background_tree is not None:
                clearance, _ = background_tree.query(means[chosen[within]])
                within = within[(clearance > contact_factor * spacing) | confirmed_in_mask[within]]
            keep[within] = True
            stats["hidden_reached"] += int(within.size)
            stats["reached_in_masks"] += int(confirmed_in_mask[within].sum())
        out[chosen[keep]] = label
        stats["hidden_taken"] += int(keep.sum())
    return out, stats


def settle_by_masks(
    labels: np.ndarray,
    means: np.ndarray,
    table: np.ndarray,
    spacing: float,
    agreement: float = DEFAULT_SETTLE_AGREEMENT,
    contact_factor: float = DEFAULT_CONTACT_FACTOR,
    join_ratio: float = DEFAULT_JOIN_RATIO,
    min_views: int = 2,
    min_share: float = 0.5,
    min_seen: int = 5,
) -> Tuple[np.ndarray, Dict[str, int]]:
    """Labels after the settle rule (module docstring), against the instances as the rules before left them. Stats:
    the Gaussians moved, and of them those that were background."""
    out = labels.copy()
    stats = {"settled": 0, "settled_from_background": 0}
    finite = np.isfinite(means).all(axis=1)
    instances = [int(label) for label in np.unique(labels[labels >= 0])]
    if len(instances) == 0:
        return out, stats
    homes = np.stack(
        [sitting_masks(table, np.flatnonzero(labels == label), min_share, min_seen) for label in instances]
    )
    # background's mask is "none" in every view: a background Gaussian is told apart from an instance wherever the
    # instance sits in a mask
    homes = np.concatenate([homes, np.zeros((1, table.shape[0]), dtype=homes.dtype)])
    row_of = np.full(int(labels.max()) + 1, len(instances))  # each label's row of homes
    row_of[instances] = np.arange(len(instances))
    best = np.zeros(labels.size)
    target = np.full(labels.size, -1)
    reach = contact_factor * spacing
    sizes = np.bincount(labels[labels >= 0])
    # only a Gaussian seen in some mask in min_views views can move: counted view by view (the table is [V, N])
    in_masks = np.zeros(labels.size, dtype=np.int64)
    for row_of_view in table:
        in_masks += row_of_view >= 1
    movable = np.flatnonzero(finite & (in_masks >= min_views))
    movable_means, movable_labels = means[movable], labels[movable]
    movable_sizes = np.where(movable_labels >= 0, sizes[np.maximum(movable_labels, 0)], 0)
    for row, label in enumerate(instances):
        members = np.flatnonzero(labels == label)
        low, high = _grown_box(means[members], reach)
        # not from a container into a small object in or on it (at most join_ratio of its size): that contact is
        # the contact rule's, whose masks split about evenly there
        smaller = movable_sizes * join_ratio < members.size
        candidates = movable[(movable_labels != label) & smaller & _in_box(movable_means, (low, high))]
        if candidates.size == 0:
            continue
        # bounded by the reach: a far candidate's search stops early (most of a large instance's box is far)
        distance, _ = cKDTree(means[members]).query(means[candidates], distance_upper_bound=reach, workers=-1)
        candidates = candidates[distance <= reach]
        home = homes[row][:, None]
        # a chunk of candidates at a time: their [V, C] sightings stay small on scenes of millions
        for chunk in np.array_split(candidates, max(1, candidates.size // SETTLE_CHUNK)):
            sightings = table[:, chunk]
            own = labels[chunk]
            own_home = homes[np.where(own >= 0, row_of[np.maximum(own, 0)], len(instances))].T  # [V, C]
            telling = (home >= 1) & (sightings >= 0) & (own_home != home)
            inside = ((sightings == home) & telling).sum(axis=0)
            share = inside / np.maximum(telling.sum(axis=0), 1)
            better = (inside >= min_views) & (share >= agreement) & (share > best[chunk])
            best[chunk[better]] = share[better]
            target[chunk[better]] = label
    moving = target >= 0
    # one Gaussian at a time, never an instance's majority: whole instances are the join rule's to move
    leaving = np.bincount(labels[moving & (labels >= 0)], minlength=sizes.size)
    drained = np.flatnonzero(leaving * 2 >= np.maximum(sizes, 1))  # an instance would lose half or more
    moving &= ~np.isin(labels, drained)
    out[moving] = target[moving]
    stats["settled"] = int(moving.sum())
    stats["settled_from_background"] = int((moving & (labels < 0)).sum())
    return out, stats


def rehome_hidden(
    labels: np.ndarray,
    means: np.ndarray,
    table: np.ndarray,
    spacing: float,
    margin: float = DEFAULT_HIDDEN_MARGIN,
    size_ratio: float = DEFAULT_JOIN_RATIO,
) -> Tuple[np.ndarray, Dict[str, int]]:
    """Labels after the rehome rule (module docstring); stats: the Gaussians moved."""
    out = labels.copy()
    finite = np.isfinite(means).all(axis=1)
    seen = (table >= 0).any(axis=0) & finite
    ids = [int(i) for i in np.unique(labels) if i >= 0]
    candidates = np.flatnonzero(~seen & finite & (labels >= 0))
    if len(ids) < 2 or candidates.size == 0:
        return out, {"rehomed": 0}
    points, own = means[candidates], labels[candidates]
    # one instance at a time, no [instances, candidates] array (millions of candidates on a large scene)
    in_own = np.zeros(candidates.size, dtype=bool)
    holding = np.zeros(candidates.size, dtype=np.int64)  # other instances' hulls that hold it by the margin
    target = np.full(candidates.size, -1, dtype=np.int64)
    for label in ids:
        depth = _hull_depth(points, means[(labels == label) & seen])
        mine = own == label
        in_own |= mine & (depth >= 0.0)
        deep = ~mine & (depth >= margin * spacing)
        holding += deep
        target[deep] = label
    sizes = np.bincount(labels[labels >= 0])
    # not from a small object into its container (over 1 / size_ratio times its size): the small object's hidden
    # side lies inside the container's hull and outside the hull of its own seen Gaussians
    moving = (holding == 1) & ~in_own
    moving[moving] &= sizes[own[moving]] >= size_ratio * sizes[target[moving]]
    out[candidates[moving]] = target[moving]
    return out, {"rehomed": int(moving.sum())}


def whole_objects(
    labels: np.ndarray,
    means: np.ndarray,
    table: np.ndarray,
    spacing: float,
    join: bool = True,
    floaters: bool = True,
    hidden: bool = True,
    unseen: bool = True,
    contact: bool = True,
    settle: bool = True,
    join_ratio: float = DEFAULT_JOIN_RATIO,
    join_agreement: float = DEFAULT_JOIN_AGREEMENT,
    contact_factor: float = DEFAULT_CONTACT_FACTOR,
    hidden_neighbours: int = DEFAULT_HIDDEN_NEIGHBOURS,
    hidden_margin: float = DEFAULT_HIDDEN_MARGIN,
    hidden_reach: float = DEFAULT_HIDDEN_REACH,
    contact_ratio: float = DEFAULT_CONTACT_RATIO,
    reach_in_masks: bool = True,
    settle_agreement: float = DEFAULT_SETTLE_AGREEMENT,
    unseen_min_seen: bool = True,
    rehome: bool = DEFAULT_REHOME,
    orphans: bool = DEFAULT_ORPHANS,
    orphan_cover: float = DEFAULT_ORPHAN_COVER,
    min_views: int = 2,
    min_share: float = 0.5,
    min_seen: int = 5,
    votes: Optional[np.ndarray] = None,
    join_vote_factor: Optional[float] = None,
) -> Tuple[np.ndarray, np.ndarray, Dict[str, Any]]:
    """One level's labels [N] (-1: background) after the rules of the module docstring, renumbered
    by decreasing size; the instances' confidence [K]; and what each rule did. ``spacing``: the
    foreground's typical spacing; ``table`` [V, N]: the mask check's per-view mask table;
    ``votes`` [N, 3] (NaN: none) with ``join_vote_factor`` adds vote proximity to the join rule."""
    from votesplat_ns.core.clustering import relabel_by_size

    for name, value in (
        ("join_ratio", join_ratio),
        ("join_agreement", join_agreement),
        ("settle_agreement", settle_agreement),
        ("orphan_cover", orphan_cover),
    ):
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"{name} must be in [0, 1], got {value}")
    if contact_factor < 0 or hidden_margin < 0 or hidden_reach < 0 or hidden_neighbours < 1 or contact_ratio < 0:
        raise ValueError(
            "contact_factor, hidden_margin, hidden_reach and contact_ratio must be >= 0 and hidden_neighbours >= 1"
        )
    out = np.asarray(labels, dtype=np.int64)
    means = np.asarray(means, dtype=np.float64)
    stats: Dict[str, Any] = {}
    if join:
        out, stats["join"] = join_fragments(
            out,
            means,
            table,
            spacing,
            join_ratio,
            join_agreement,
            contact_factor,
            min_views,
            min_share,
            min_seen,
            None if votes is None else np.asarray(votes, dtype=np.float64),
            join_vote_factor,
        )
    if orphans:
        out, stats["orphans"] = adopt_orphans(
            out, means, table, spacing, join_ratio, contact_factor, min_views, min_share, min_seen, orphan_cover
        )
    if floaters:
        out, stats["floaters"] = drop_floaters(
            out, means, table, spacing, contact_factor, min_views, unseen, min_seen if unseen_min_seen else 1
        )
    if settle:
        out, stats["settle"] = settle_by_masks(
            out, means, table, spacing, settle_agreement, contact_factor, join_ratio, min_views, min_share, min_seen
        )
    if contact:
        out, stats["contact"] = take_contact(
            out, means, table, spacing, contact_ratio, hidden_reach, join_ratio, min_views, min_share, min_seen
        )
    if hidden:
        out, stats["hidden"] = take_hidden(
            out,
            means,
            table,
            spacing,
            hidden_neighbours=hidden_neighbours,
            hidden_margin=hidden_margin,
            min_share=min_share,
            min_seen=min_seen,
            hidden_reach=hidden_reach,
            contact_factor=contact_factor,
            reach_in_masks=reach_in_masks,
        )
    if rehome:
        out, stats["rehome"] = rehome_hidden(out, means, table, spacing, hidden_margin, join_ratio)
    out = relabel_by_size(out)
    confidence = instance_confidence(out, table, min_views, min_share, min_seen)
    stats["num_instances"] = int(confidence.size)
    return out, confidence, stats
