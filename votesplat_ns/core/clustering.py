"""Instances from 3D votes: background filtering and HDBSCAN clustering (paper §3.4).

Every Gaussian i votes for its instance centre at V_i = p_i + Δp_i (one vote per SAM level).
Gaussians that never received vote supervision at a level are background there (paper: "Δp = 0";
we test the model's per-level ``vote_support`` count instead, which does not depend on an offset
staying exactly zero). The remaining votes are clustered with HDBSCAN; each cluster is an instance.

Scaling. HDBSCAN is run on a seeded random subsample of at most ``max_points`` votes and every
other vote takes the label of its nearest subsampled vote (k-d tree). Random subsampling keeps the
*relative* vote density, which is what HDBSCAN's density levels are made of; voxel downsampling
would flatten it (a converged instance collapses to a few voxels), so we do not use it. Because
``min_cluster_size`` is given in votes of the full set, it is scaled by the subsample fraction.

Identical votes. A converged instance votes for (almost) one point. Exact or near duplicates give
HDBSCAN infinite densities, which makes its Borůvka tree slow and its cluster choice arbitrary, so
the subsample is smoothed by a deterministic jitter of ``smoothing`` (default 1e-3 of the vote
spread): structure below that scale is ignored.

Noise rule (``noise``):
  * "drop": a vote keeps HDBSCAN's decision: subsampled votes their own label, the others the
    label of their nearest subsampled vote, so votes next to outliers stay -1 (noise).
  * "nearest" (default): as "drop", then every vote still at -1 joins the instance of its nearest
    non-noise subsampled vote if that one is within ``noise_radius`` (default 2% of the vote
    spread, i.e. of the 1-99 percentile bounding-box diagonal); otherwise it stays -1. Exports then
    carry whole objects (HDBSCAN labels a blob's sparse fringe as noise) while true strays stay out.

Holes and fragments (``fill``, in :func:`cluster_levels`): every foreground Gaussian votes, so a
foreground Gaussian that the vote clustering leaves as noise (a badly converged vote inside an
object), or that sits in a fragment smaller than ``min_instance_fraction`` of the foreground, takes
the instance that most of its spatial neighbours (Gaussian centres, not votes) hold, when they lie
within ``fill_radius_factor`` times the foreground's typical spacing (median distance of a
Gaussian to its ``fill_neighbours``-th nearest foreground neighbour). Repeated until nothing
changes, so a hole fills from its rim inwards. A Gaussian with no labelled neighbour that close
stays noise, and a fragment that nothing reaches stays an instance of its own (a small object
far from everything else). Both scales are relative to the scene's own spacing.

Over-split objects (``merge_separation``, in :func:`cluster_levels`): an object whose votes did not
converge to one point (large, flat or seen from one side) spreads them, and HDBSCAN may cut the
spread into several clusters. Two clusters merge when their vote centres (medians) are closer than
``merge_separation`` times the sum of their vote spreads (median distance of a cluster's votes to
its centre); merges are transitive. The test compares the gap with the clusters' own spread, so it
holds at any scene scale: converged neighbours (small spreads) stay apart however close they are.

Labels are renumbered 0..K-1 by decreasing cluster size (ties: smallest first member), so the
result is deterministic for a fixed seed and independent of HDBSCAN's internal numbering.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Literal, Optional, Sequence, Tuple

import numpy as np

from votesplat_ns.core.instances import InstanceSet, LevelInstances

NoiseRule = Literal["nearest", "drop"]

DEFAULT_MAX_POINTS = 50_000
# Smallest instance, as a fraction of the foreground votes, that the defaults look for.
DEFAULT_MIN_CLUSTER_FRACTION = 5e-4
DEFAULT_NOISE_RADIUS_FRACTION = 0.02
DEFAULT_SMOOTHING_FRACTION = 1e-3
# Spatial fill of noise and fragments (module docstring, "Holes and fragments").
DEFAULT_FILL_NEIGHBOURS = 8
DEFAULT_FILL_RADIUS_FACTOR = 3.0
# Fragment dissolution is off: on the tuning scenes it absorbed small objects resting on
# larger ones (stacked, fruit in a bowl); the noise fill alone kept them (BENCHMARKS.md,
# "Instance quality on the scene family").
DEFAULT_MIN_INSTANCE_FRACTION = 0.0
_FILL_MAX_ROUNDS = 64


@dataclass
class VoteClustering:
    """Labels of one clustering run and every parameter it actually used (for manifests)."""

    labels: np.ndarray  # [M] int64, -1 = noise
    params: Dict[str, Any] = field(default_factory=dict)

    @property
    def num_clusters(self) -> int:
        return int(self.labels.max()) + 1 if self.labels.size else 0


def _to_numpy(array) -> np.ndarray:
    if hasattr(array, "detach"):
        array = array.detach().cpu().numpy()
    return np.asarray(array)


def vote_spread(votes: np.ndarray) -> float:
    """Robust scene scale of the votes: diagonal of their 1st-99th percentile bounding box."""
    if votes.shape[0] == 0:
        return 0.0
    low, high = np.percentile(votes, [1.0, 99.0], axis=0)
    return float(np.linalg.norm(high - low))


def default_min_cluster_size(num_votes: int, fraction: float = DEFAULT_MIN_CLUSTER_FRACTION) -> int:
    """Smallest instance the defaults look for, in votes: ``fraction`` of the votes (0.05%), at least 10."""
    return max(10, int(math.ceil(fraction * num_votes)))


def relabel_by_size(labels: np.ndarray) -> np.ndarray:
    """Renumber clusters 0..K-1 by decreasing size (ties: earliest first member); -1 stays -1."""
    clustered = labels >= 0
    if not clustered.any():
        return labels.copy()
    old_ids, first, counts = np.unique(labels[clustered], return_index=True, return_counts=True)
    order = np.lexsort((first, -counts))
    mapping = np.full(int(old_ids.max()) + 1, -1, dtype=np.int64)
    mapping[old_ids[order]] = np.arange(order.size)
    out = np.full(labels.shape, -1, dtype=np.int64)
    out[clustered] = mapping[labels[clustered]]
    return out


def cluster_votes_detailed(
    votes,
    min_cluster_size: Optional[int] = None,
    min_samples: Optional[int] = None,
    max_points: int = DEFAULT_MAX_POINTS,
    seed: int = 0,
    noise: NoiseRule = "nearest",
    noise_radius: Optional[float] = None,
    smoothing: Optional[float] = None,
    cluster_selection_epsilon: float = 0.0,
    n_jobs: Optional[int] = None,
    min_cluster_fraction: float = DEFAULT_MIN_CLUSTER_FRACTION,
) -> VoteClustering:
    """HDBSCAN on 3D votes [M, 3] with subsampling and the noise rule of the module docstring.

    min_cluster_size: smallest instance in votes of the full set (default: ``min_cluster_fraction`` of M, >= 10).
    min_samples: HDBSCAN's density smoothing, in subsampled votes (default min(10, scaled size)).
    max_points: the most votes HDBSCAN sees; the rest are labelled by nearest neighbour.
    noise_radius / smoothing: distances in vote units (defaults from the vote spread, above).
    cluster_selection_epsilon: HDBSCAN's merge distance (0 = plain HDBSCAN, as in the paper).
    n_jobs: threads for the nearest-neighbour label transfer (default: CPU count, at most 4).
    """
    import hdbscan  # heavy import (numba/sklearn), only when clustering
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  (compiled, no stubs)

    votes = _to_numpy(votes).astype(np.float64, copy=False)
    if votes.ndim != 2 or votes.shape[1] != 3:
        raise ValueError(f"votes must have shape [M, 3], got {list(votes.shape)}")
    if noise not in ("nearest", "drop"):
        raise ValueError(f"noise must be 'nearest' or 'drop', got {noise!r}")
    if max_points < 2:
        raise ValueError(f"max_points must be at least 2, got {max_points}")
    bad = ~np.isfinite(votes).all(axis=1)
    if bad.any():
        raise ValueError(
            f"{int(bad.sum())} of {votes.shape[0]} votes are NaN/Inf; drop those Gaussians before clustering"
        )
    num_votes = votes.shape[0]
    if num_votes == 0:
        raise ValueError("no votes to cluster (the vote array is empty)")

    spread = vote_spread(votes)
    if min_cluster_size is None:
        if not 0.0 < min_cluster_fraction < 1.0:
            raise ValueError(f"min_cluster_fraction must be in (0, 1), got {min_cluster_fraction}")
        min_cluster_size = default_min_cluster_size(num_votes, min_cluster_fraction)
    if min_cluster_size < 2:
        raise ValueError(f"min_cluster_size must be at least 2, got {min_cluster_size}")
    if noise_radius is None:
        noise_radius = DEFAULT_NOISE_RADIUS_FRACTION * spread
    if smoothing is None:
        smoothing = DEFAULT_SMOOTHING_FRACTION * spread
    if noise_radius < 0 or smoothing < 0 or cluster_selection_epsilon < 0:
        raise ValueError("noise_radius, smoothing and cluster_selection_epsilon must be >= 0")

    rng = np.random.default_rng(seed)
    if num_votes > max_points:
        sample_index = np.sort(rng.choice(num_votes, size=max_points, replace=False))
    else:
        sample_index = np.arange(num_votes)
    num_sample = sample_index.size
    fraction = num_sample / num_votes
    sample_min_cluster_size = max(2 if num_sample == num_votes else 5, int(round(min_cluster_size * fraction)))
    if min_samples is None:
        min_samples = min(10, sample_min_cluster_size)
    if min_samples < 1:
        raise ValueError(f"min_samples must be at least 1, got {min_samples}")
    if n_jobs is None:
        n_jobs = max(1, min(4, os.cpu_count() or 1))

    params: Dict[str, object] = {
        "algorithm": "hdbscan",
        "num_votes": int(num_votes),
        "min_cluster_size": int(min_cluster_size),
        "min_samples": int(min_samples),
        "max_points": int(max_points),
        "num_clustered_points": int(num_sample),
        "sample_min_cluster_size": int(sample_min_cluster_size),
        "seed": int(seed),
        "noise": noise,
        "noise_radius": float(noise_radius),
        "smoothing": float(smoothing),
        "cluster_selection_epsilon": float(cluster_selection_epsilon),
        "vote_spread": float(spread),
    }

    sample = votes[sample_index]
    if num_sample < max(sample_min_cluster_size, min_samples + 1, 2):
        sample_labels = np.full(num_sample, -1, dtype=np.int64)
    else:
        jittered = sample + rng.normal(0.0, 1.0, sample.shape) * smoothing if smoothing > 0 else sample
        clusterer = hdbscan.HDBSCAN(
            min_cluster_size=int(sample_min_cluster_size),
            min_samples=int(min_samples),
            cluster_selection_epsilon=float(cluster_selection_epsilon),
            algorithm="boruvka_kdtree",
            # hdbscan parallelises core distances with joblib worker *processes*; starting them
            # costs seconds, more than the 50k-point core-distance query they would share
            core_dist_n_jobs=1,
        )
        sample_labels = clusterer.fit_predict(jittered).astype(np.int64)

    labels = np.full(num_votes, -1, dtype=np.int64)
    labels[sample_index] = sample_labels
    if num_sample < num_votes:
        rest = np.ones(num_votes, dtype=bool)
        rest[sample_index] = False
        _, nearest = cKDTree(sample).query(votes[rest], k=1, workers=n_jobs)
        labels[rest] = sample_labels[nearest]

    if noise == "nearest":
        members = sample_labels >= 0
        unlabelled = np.flatnonzero(labels < 0)
        if members.any() and unlabelled.size:
            tree = cKDTree(sample[members])
            distance, nearest = tree.query(
                votes[unlabelled], k=1, distance_upper_bound=noise_radius * (1 + 1e-9), workers=n_jobs
            )
            close = np.isfinite(distance)
            labels[unlabelled[close]] = sample_labels[members][nearest[close]]

    labels = relabel_by_size(labels)
    params["num_clusters"] = int(labels.max()) + 1 if (labels >= 0).any() else 0
    params["num_noise"] = int((labels < 0).sum())
    return VoteClustering(labels=labels, params=params)


def typical_spacing(points: np.ndarray, neighbours: int = DEFAULT_FILL_NEIGHBOURS) -> float:
    """Median distance of a point to its ``neighbours``-th nearest other point (0 if too few)."""
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  (compiled, no stubs)

    points = np.asarray(points, dtype=np.float64)
    if points.shape[0] <= neighbours:
        return 0.0
    distance, _ = cKDTree(points).query(points, k=neighbours + 1)
    return float(np.median(distance[:, -1]))


def fill_from_neighbours(
    points: np.ndarray,
    labels: np.ndarray,
    neighbours: int = DEFAULT_FILL_NEIGHBOURS,
    radius_factor: float = DEFAULT_FILL_RADIUS_FACTOR,
    min_instance_fraction: float = DEFAULT_MIN_INSTANCE_FRACTION,
) -> np.ndarray:
    """Labels [M] after the spatial fill of the module docstring ("Holes and fragments").

    points [M, 3]: the foreground Gaussians' centres; labels [M] int: clusters 0..K-1, -1 noise.
    Returns new labels renumbered by decreasing size; -1 only where no labelled Gaussian is near.
    """
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  (compiled, no stubs)

    points = np.asarray(points, dtype=np.float64)
    labels = np.asarray(labels, dtype=np.int64).copy()
    if points.shape[0] != labels.shape[0]:
        raise ValueError(f"{points.shape[0]} points but {labels.shape[0]} labels")
    if neighbours < 1 or radius_factor < 0 or not 0.0 <= min_instance_fraction < 1.0:
        raise ValueError("fill needs neighbours >= 1, radius_factor >= 0 and min_instance_fraction in [0, 1)")
    m = points.shape[0]
    if m <= neighbours or not (labels >= 0).any():
        return relabel_by_size(labels)
    radius = radius_factor * typical_spacing(points, neighbours)
    if radius <= 0:
        return relabel_by_size(labels)

    original = labels.copy()
    sizes = np.bincount(labels[labels >= 0])
    fragments = np.flatnonzero(sizes < min_instance_fraction * m)
    if fragments.size < sizes.size:  # a fragment dissolves only into a larger instance
        labels[np.isin(labels, fragments)] = -1
    for _ in range(_FILL_MAX_ROUNDS):
        open_index = np.flatnonzero(labels < 0)
        labelled = np.flatnonzero(labels >= 0)
        if open_index.size == 0 or labelled.size == 0:
            break
        k = min(neighbours, labelled.size)
        near_distance, near = cKDTree(points[labelled]).query(points[open_index], k=k, distance_upper_bound=radius)
        near_distance, near = near_distance.reshape(open_index.size, k), near.reshape(open_index.size, k)
        found = np.isfinite(near_distance)
        reached = found.any(axis=1)
        if not reached.any():
            break
        near_labels = np.where(found, labels[labelled[np.minimum(near, labelled.size - 1)]], -1)
        # majority of the labelled neighbours found; the query sorts them nearest first and argmax
        # takes the first maximum, so a tie goes to the nearest of the tied labels
        votes = ((near_labels[:, :, None] == near_labels[:, None, :]) & found[:, None, :]).sum(axis=2)
        votes = np.where(found, votes, -1)
        winner = near_labels[np.arange(open_index.size), votes.argmax(axis=1)]
        labels[open_index] = np.where(reached, winner, -1)
    # a fragment that nothing reached stays an instance of its own
    unreached = (labels < 0) & np.isin(original, fragments)
    labels[unreached] = original[unreached]
    return relabel_by_size(labels)


def merge_spread_clusters(votes: np.ndarray, labels: np.ndarray, separation: float) -> np.ndarray:
    """Labels [M] after merging clusters whose vote centres are closer than ``separation`` times
    the sum of their vote spreads (module docstring, "Over-split objects"); renumbered by size."""
    votes = np.asarray(votes, dtype=np.float64)
    labels = np.asarray(labels, dtype=np.int64)
    if separation < 0:
        raise ValueError(f"merge separation must be >= 0, got {separation}")
    ids = np.unique(labels[labels >= 0])
    if ids.size < 2 or separation == 0:
        return relabel_by_size(labels)
    centres = np.stack([np.median(votes[labels == k], axis=0) for k in ids])
    spreads = np.array([np.median(np.linalg.norm(votes[labels == k] - c, axis=1)) for k, c in zip(ids, centres)])
    gap = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    close = gap < separation * (spreads[:, None] + spreads[None, :])
    root = np.arange(ids.size)

    def find(i: int) -> int:
        while root[i] != i:
            root[i] = root[root[i]]
            i = root[i]
        return i

    for a, b in zip(*np.nonzero(np.triu(close, k=1))):
        root[find(a)] = find(b)
    mapping = np.full(int(ids.max()) + 1, -1, dtype=np.int64)
    mapping[ids] = [find(i) for i in range(ids.size)]
    merged = np.where(labels >= 0, mapping[np.maximum(labels, 0)], -1)
    return relabel_by_size(merged)


def background_mask(vote_support, level: int) -> np.ndarray:
    """[N] bool, True for Gaussians that received no vote supervision at ``level`` (background).

    vote_support [N, L] counts the supervised pixels each Gaussian voted for at each level; the model
    negates the count of Gaussians whose rendering weight lies mostly outside the masks (see
    ``votesplat_ns.core.foreground``), so only > 0 is foreground.
    """
    support = _to_numpy(vote_support)
    if support.ndim != 2:
        raise ValueError(f"vote_support must have shape [N, L], got {list(support.shape)}")
    if not -support.shape[1] <= level < support.shape[1]:
        raise ValueError(f"level {level} is out of range for vote_support with {support.shape[1]} levels")
    column = support[:, level]
    if not np.isfinite(column).all():
        raise ValueError("vote_support contains NaN/Inf; the checkpoint is corrupt, re-export from a finite model")
    return ~(column > 0)


@dataclass(frozen=True)
class ClusteringOptions:
    """The HDBSCAN settings a command sets for :func:`cluster_levels` (export, query, click); the defaults are its own.

    ``min_cluster_size`` and ``min_samples`` are in votes (None: scaled defaults), ``max_points`` the
    most votes HDBSCAN clusters, ``seed`` its subsample, ``noise``/``noise_radius`` the noise rule,
    ``cluster_selection_epsilon`` HDBSCAN's merge distance; see :func:`cluster_votes_detailed`.
    """

    min_cluster_size: Optional[int] = None
    min_samples: Optional[int] = None
    max_points: int = DEFAULT_MAX_POINTS
    seed: int = 0
    noise: NoiseRule = "nearest"
    noise_radius: Optional[float] = None
    cluster_selection_epsilon: float = 0.0
    coarse_to_fine: bool = True

    def kwargs(self) -> Dict[str, Any]:
        """The settings as :func:`cluster_levels` keyword arguments."""
        return {name: getattr(self, name) for name in self.__dataclass_fields__}


def cluster_levels(
    means,
    offsets,
    support,
    level_names: Sequence[str],
    coarse_to_fine: bool = True,
    on_level: Optional[Callable[[int, str], None]] = None,
    fill: bool = True,
    min_instance_fraction: float = DEFAULT_MIN_INSTANCE_FRACTION,
    merge_separation: Optional[float] = None,
    refine: Optional[Callable[[int, str, np.ndarray], Tuple[np.ndarray, Dict[str, Any]]]] = None,
    **cluster_kwargs: Any,
) -> InstanceSet:
    """Instances of every vote level, linked parent -> child between consecutive levels.

    means [N, 3], offsets [N, L, 3] (vote = means + offsets[:, l]), support [N, L] (> 0: the
    Gaussian is foreground at level l). Gaussians with a non-finite mean or offset count as
    background. With ``coarse_to_fine`` (levels listed coarsest first, e.g. ("instance", "part"))
    the parent of an instance at level l is the level l-1 instance holding most of its Gaussians;
    otherwise the parent level is l+1. A level without foreground gets no instances (no error
    here: the exporter decides which levels it needs). ``on_level(index, name)`` is called before
    each level is clustered (progress reporting). ``fill`` gives foreground noise and fragments
    smaller than ``min_instance_fraction`` of the level's foreground the instance of their spatial
    neighbours (:func:`fill_from_neighbours`). ``merge_separation`` (None: off) first merges
    clusters of spread votes (:func:`merge_spread_clusters`). ``refine(index, name, ids)`` (ids [N],
    -1 outside every instance) returns new ids and a dict of counts stored with the level's
    clustering parameters (an array under ``"confidence"`` becomes the level's per-instance
    confidence; a background Gaussian it puts in an instance becomes foreground); the exporter passes the training-mask check
    (:func:`votesplat_ns.core.mask_consensus.regroup_with_masks`) here. ``cluster_kwargs`` are the
    HDBSCAN settings of :func:`cluster_votes_detailed` (``min_cluster_size``, ``min_samples``,
    ``max_points``, ``seed``, ``noise``, ...), the same for every level.
    """
    means = _to_numpy(means)
    offsets = _to_numpy(offsets)
    support = _to_numpy(support)
    n = means.shape[0] if means.ndim == 2 else -1
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"means must have shape [N, 3], got {list(means.shape)}")
    if offsets.ndim != 3 or offsets.shape[0] != n or offsets.shape[2] != 3:
        raise ValueError(f"vote offsets must have shape [N, L, 3] with N={n}, got {list(offsets.shape)}")
    num_levels = offsets.shape[1]
    if support.shape != (n, num_levels):
        raise ValueError(f"vote_support must have shape [N, L] = [{n}, {num_levels}], got {list(support.shape)}")
    level_names = tuple(str(name) for name in level_names)
    if len(level_names) != num_levels:
        raise ValueError(
            f"{len(level_names)} level names {level_names} for {num_levels} vote levels; pass one name per level"
        )
    if len(set(level_names)) != num_levels:
        raise ValueError(f"level names must be unique, got {level_names}")

    finite_means = np.isfinite(means).all(axis=1)
    levels = []
    for index, name in enumerate(level_names):
        if on_level is not None:
            on_level(index, name)
        foreground = ~background_mask(support, index) & finite_means & np.isfinite(offsets[:, index]).all(axis=1)
        fg_index = np.flatnonzero(foreground)
        votes = means[fg_index].astype(np.float64) + offsets[fg_index, index].astype(np.float64)
        ids = np.full(n, -1, dtype=np.int64)
        confidence: Optional[np.ndarray] = None
        if fg_index.size:
            result = cluster_votes_detailed(votes, **cluster_kwargs)
            labels = result.labels
            params = dict(result.params)
            if merge_separation is not None:
                labels = merge_spread_clusters(votes, labels, merge_separation)
                params.update(
                    merge_separation=float(merge_separation),
                    num_clusters_before_merge=int(result.params["num_clusters"]),
                )
            if fill:
                labels = fill_from_neighbours(means[fg_index], labels, min_instance_fraction=min_instance_fraction)
                params.update(
                    fill="spatial",
                    fill_neighbours=DEFAULT_FILL_NEIGHBOURS,
                    fill_radius_factor=DEFAULT_FILL_RADIUS_FACTOR,
                    min_instance_fraction=float(min_instance_fraction),
                    num_clusters=int(labels.max()) + 1 if (labels >= 0).any() else 0,
                    num_noise=int((labels < 0).sum()),
                    num_noise_before_fill=int(result.params["num_noise"]),
                )
            params["num_clusters"] = int(labels.max()) + 1 if (labels >= 0).any() else 0
            ids[fg_index] = labels
            if refine is not None:
                ids, refine_stats = refine(index, name, ids)
                ids = np.asarray(ids, dtype=np.int64)
                refine_stats = dict(refine_stats)
                confidence = refine_stats.pop("confidence", None)
                params.update(mask_check=refine_stats, num_clusters=int(ids.max()) + 1 if (ids >= 0).any() else 0)
                # a Gaussian that never voted but joined an object (hidden behind its surface) is
                # the object's: foreground at this level from now on
                params["num_joined_background"] = int(((ids >= 0) & ~foreground).sum())
                foreground = foreground | (ids >= 0)
        else:
            params = {"algorithm": "hdbscan", "num_votes": 0, "num_clusters": 0, "num_noise": 0}
        vote_points = np.full((n, 3), np.nan)
        vote_points[fg_index] = votes
        levels.append(LevelInstances.from_ids(name, ids, foreground, means, vote_points, params, confidence))

    parent_levels = []
    for child in range(num_levels):
        parent = child - 1 if coarse_to_fine else child + 1
        if 0 <= parent < num_levels:
            levels[child].link_parents(levels[parent])
            parent_levels.append(level_names[parent])
        else:
            parent_levels.append(None)
    return InstanceSet(levels=levels, num_gaussians=n, parent_levels=parent_levels)
