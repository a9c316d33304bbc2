"""HDBSCAN vote clustering: exact separation, subsampling, determinism, noise rule, levels."""

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from votesplat_ns.core.clustering import (
    background_mask,
    cluster_levels,
    cluster_votes_detailed,
    default_min_cluster_size,
    fill_from_neighbours,
    merge_spread_clusters,
)


def cluster_votes(votes, **options):
    """The labels alone of ``cluster_votes_detailed``."""
    return cluster_votes_detailed(votes, **options).labels


def blobs(num_blobs=5, per_blob=200, spread=0.05, separation=4.0, strays=0, seed=0):
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-separation, separation, size=(num_blobs, 3))
    # keep blobs far apart relative to their size so the truth is unambiguous
    while min(np.linalg.norm(a - b) for i, a in enumerate(centres) for b in centres[i + 1 :]) < 1.0:
        centres = rng.uniform(-separation, separation, size=(num_blobs, 3))
    truth = np.repeat(np.arange(num_blobs), per_blob)
    votes = centres[truth] + rng.normal(0, spread, size=(truth.size, 3))
    if strays:
        votes = np.concatenate([votes, rng.uniform(-separation - 1, separation + 1, size=(strays, 3))])
        truth = np.concatenate([truth, np.full(strays, -1)])
    order = rng.permutation(truth.size)
    return votes[order], truth[order]


def agreement(a, b):
    """Fraction of points on which two labelings agree after the best one-to-one label matching."""
    ua, ia = np.unique(a, return_inverse=True)
    ub, ib = np.unique(b, return_inverse=True)
    table = np.zeros((ua.size, ub.size))
    np.add.at(table, (ia, ib), 1)
    rows, cols = linear_sum_assignment(-table)
    return table[rows, cols].sum() / a.size


@pytest.mark.parametrize("noise", ["nearest", "drop"])
def test_separates_blobs_exactly(noise):
    votes, truth = blobs(num_blobs=5, per_blob=200)
    labels = cluster_votes(votes, noise=noise)
    assert labels.min() >= 0 and labels.max() == 4
    # exact match up to a permutation: every blob is one label and every label is one blob
    pairs = set(zip(truth.tolist(), labels.tolist()))
    assert len(pairs) == 5


def test_labels_are_numbered_by_decreasing_size():
    rng = np.random.default_rng(1)
    sizes = [150, 400, 60]
    votes = np.concatenate([c + rng.normal(0, 0.05, (s, 3)) for c, s in zip(np.eye(3) * 5, sizes)])
    labels = cluster_votes(votes, noise="nearest")
    assert np.bincount(labels).tolist() == sorted(sizes, reverse=True)


def test_subsample_and_assign_agrees_with_full_clustering():
    votes, _ = blobs(num_blobs=8, per_blob=2000, spread=0.1, separation=5.0, strays=160, seed=2)
    full = cluster_votes_detailed(votes, max_points=votes.shape[0])
    sub = cluster_votes_detailed(votes, max_points=4000)
    assert full.params["num_clustered_points"] == votes.shape[0]
    assert sub.params["num_clustered_points"] == 4000
    assert full.num_clusters == sub.num_clusters == 8
    assert agreement(full.labels, sub.labels) >= 0.99


def test_deterministic_for_a_fixed_seed():
    votes, _ = blobs(num_blobs=4, per_blob=1500, spread=0.1, strays=100, seed=3)
    first = cluster_votes(votes, max_points=2000, seed=7)
    second = cluster_votes(votes, max_points=2000, seed=7)
    np.testing.assert_array_equal(first, second)
    other_seed = cluster_votes(votes, max_points=2000, seed=8)
    assert agreement(first, other_seed) >= 0.98  # a different subsample, the same instances


def test_identical_votes_are_handled():
    # a converged instance votes for one point: duplicates must not break HDBSCAN
    centres = np.array([[0.0, 0, 0], [3.0, 0, 0], [0, 3.0, 0]])
    votes = np.repeat(centres, 500, axis=0)
    labels = cluster_votes(votes)
    assert len(set(zip(np.repeat(np.arange(3), 500).tolist(), labels.tolist()))) == 3
    assert labels.min() >= 0


def test_noise_rule():
    # strays everywhere: HDBSCAN calls them noise, some of them lie close to an instance
    votes, truth = blobs(num_blobs=3, per_blob=300, spread=0.1, strays=600, seed=4)
    far = np.array([[40.0, 40.0, 40.0]])  # an isolated stray far from everything
    votes = np.concatenate([votes, far])
    dropped = cluster_votes_detailed(votes, min_cluster_size=50, noise="drop")
    radius = 1.0
    kept = cluster_votes_detailed(votes, min_cluster_size=50, noise="nearest", noise_radius=radius)
    assert dropped.labels[-1] == kept.labels[-1] == -1
    assert (dropped.labels < 0).sum() > (kept.labels < 0).sum()
    # "nearest" only relabels noise: HDBSCAN's members keep their instance (same numbering here)
    members = dropped.labels >= 0
    assert agreement(dropped.labels[members], kept.labels[members]) == 1.0
    # a noise vote joins the instance of the nearest member iff that member is within the radius
    tree = cKDTree(votes[members])
    distance, nearest = tree.query(votes[~members])
    mapping = {d: k for d, k in zip(dropped.labels[members], kept.labels[members])}
    expected = np.where(distance <= radius, kept.labels[members][nearest], -1)
    np.testing.assert_array_equal(kept.labels[~members], expected)
    assert set(mapping) == set(range(3))
    assert kept.params["noise_radius"] == radius


def test_defaults_come_from_the_data():
    votes, _ = blobs(num_blobs=3, per_blob=1000, seed=5)
    info = cluster_votes_detailed(votes, max_points=1000).params
    assert info["min_cluster_size"] == default_min_cluster_size(3000) == 10
    assert info["sample_min_cluster_size"] == 5  # 10 votes at a 1/3 sampling rate, floor 5
    assert info["noise_radius"] == pytest.approx(0.02 * info["vote_spread"])
    assert default_min_cluster_size(1_000_000) == 500
    custom = cluster_votes_detailed(votes, min_cluster_size=300, min_samples=3, max_points=1500).params
    assert (custom["min_cluster_size"], custom["sample_min_cluster_size"], custom["min_samples"]) == (300, 150, 3)


def test_bad_votes_are_clear_errors():
    with pytest.raises(ValueError, match=r"votes must have shape \[M, 3\]"):
        cluster_votes(np.zeros((10, 2)))
    with pytest.raises(ValueError, match="NaN/Inf"):
        cluster_votes(np.array([[0.0, 0, 0], [np.nan, 0, 0]]))
    with pytest.raises(ValueError, match="empty"):
        cluster_votes(np.zeros((0, 3)))
    with pytest.raises(ValueError, match="noise must be"):
        cluster_votes(np.zeros((5, 3)), noise="keep")
    with pytest.raises(ValueError, match="min_cluster_size must be at least 2"):
        cluster_votes(np.zeros((5, 3)), min_cluster_size=1)


def test_too_few_votes_are_all_noise():
    labels = cluster_votes(np.random.default_rng(0).normal(size=(6, 3)))
    assert (labels == -1).all()


def test_background_mask():
    support = np.array([[0.0, 2.0], [5.0, 0.0], [1.0, 1.0]])
    np.testing.assert_array_equal(background_mask(support, 0), [True, False, False])
    np.testing.assert_array_equal(background_mask(support, 1), [False, True, False])
    with pytest.raises(ValueError, match="out of range"):
        background_mask(support, 2)
    with pytest.raises(ValueError, match="NaN/Inf"):
        background_mask(np.array([[np.nan]]), 0)


def two_level_scene(seed=0):
    """Four objects of two parts each; the parts vote for their own centres at level 1."""
    rng = np.random.default_rng(seed)
    objects = np.array([[0.0, 0, 0], [4.0, 0, 0], [0, 4.0, 0], [0, 0, 4.0]])
    part_of = np.repeat(np.arange(8), 150)
    object_of = part_of // 2
    part_centres = objects[np.arange(8) // 2] + np.array([[-0.6, 0, 0], [0.6, 0, 0]] * 4)
    means = part_centres[part_of] + rng.normal(0, 0.15, size=(part_of.size, 3))
    background = rng.uniform(-2, 6, size=(200, 3))
    means = np.concatenate([means, background])
    n = means.shape[0]
    offsets = np.zeros((n, 2, 3))
    offsets[: part_of.size, 0] = objects[object_of] - means[: part_of.size] + rng.normal(0, 0.02, (part_of.size, 3))
    offsets[: part_of.size, 1] = part_centres[part_of] - means[: part_of.size] + rng.normal(0, 0.02, (part_of.size, 3))
    support = np.zeros((n, 2))
    support[: part_of.size] = rng.integers(1, 5, size=(part_of.size, 2))
    return means, offsets, support, object_of, part_of


def test_cluster_levels_links_parts_to_objects():
    means, offsets, support, object_of, part_of = two_level_scene()
    instances = cluster_levels(means, offsets, support, ("instance", "part"))
    instances.validate()
    objects, parts = instances.level("instance"), instances.level("part")
    fg = part_of.size
    assert objects.num_instances == 4 and parts.num_instances == 8
    assert len(set(zip(object_of.tolist(), objects.ids[:fg].tolist()))) == 4
    assert len(set(zip(part_of.tolist(), parts.ids[:fg].tolist()))) == 8
    assert (objects.ids[fg:] == -1).all() and (parts.ids[fg:] == -1).all()
    assert not objects.foreground[fg:].any()
    # each part's parent is the object it belongs to, and it lies entirely inside it
    for part_id in range(8):
        member = np.flatnonzero(parts.ids == part_id)[0]
        assert parts.parents[part_id] == objects.ids[member]
        assert parts.parent_overlap[part_id] == 1.0
    assert (objects.parents == -1).all()
    assert instances.parent_levels == [None, "instance"]
    reverse = cluster_levels(means, offsets[:, ::-1], support[:, ::-1], ("part", "instance"), coarse_to_fine=False)
    assert reverse.parent_levels == ["instance", None]
    np.testing.assert_array_equal(reverse.level("part").parents, parts.parents)


def test_cluster_levels_treats_non_finite_gaussians_as_background():
    means, offsets, support, _, part_of = two_level_scene(seed=1)
    means[0] = np.nan
    offsets[1, 1] = np.inf
    instances = cluster_levels(means, offsets, support, ("instance", "part"))
    assert instances.level(0).ids[0] == -1 and not instances.level(0).foreground[0]
    assert instances.level(0).ids[1] >= 0 and instances.level(1).ids[1] == -1


def test_cluster_levels_bad_inputs():
    means, offsets, support, _, _ = two_level_scene()
    with pytest.raises(ValueError, match="level names"):
        cluster_levels(means, offsets, support, ("instance",))
    with pytest.raises(ValueError, match="unique"):
        cluster_levels(means, offsets, support, ("a", "a"))
    with pytest.raises(ValueError, match="vote_support must have shape"):
        cluster_levels(means, offsets, support[:, :1], ("a", "b"))
    with pytest.raises(ValueError, match="vote offsets must have shape"):
        cluster_levels(means, offsets[:-1], support, ("a", "b"))


def surface_scene(seed=0):
    """Two touching boxes' surfaces (Gaussian centres) and one small cube far away."""
    rng = np.random.default_rng(seed)
    left = rng.uniform([0, 0, 0], [1, 1, 1], size=(1500, 3))
    right = rng.uniform([1, 0, 0], [2, 1, 1], size=(1500, 3))
    far = rng.uniform([6, 6, 6], [6.2, 6.2, 6.2], size=(4, 3))
    points = np.concatenate([left, right, far])
    truth = np.repeat([0, 1, 2], [1500, 1500, 4])
    return points, truth


def test_fill_closes_holes_and_leaves_far_strays():
    points, truth = surface_scene()
    labels = truth.copy()
    rng = np.random.default_rng(1)
    holes = rng.choice(3000, size=600, replace=False)  # 20% of both boxes left as noise by the vote clustering
    labels[holes] = -1
    stray = np.array([[20.0, 20.0, 20.0]])
    filled = fill_from_neighbours(np.concatenate([points, stray]), np.concatenate([labels, [-1]]))
    assert filled[-1] == -1  # far from everything: stays unassigned
    filled = filled[:-1]
    assert (filled[:3000] >= 0).all()
    assert agreement(filled, truth) > 0.99
    # the far small cube stays an instance of its own
    assert len(set(filled[3000:])) == 1 and filled[3000] not in set(filled[:3000])


def test_fill_dissolves_fragments_into_their_object():
    points, truth = surface_scene(seed=2)
    labels = truth.copy()
    inside_left = np.flatnonzero((truth == 0) & (points[:, 0] < 0.3))[:5]
    labels[inside_left] = 3  # a 5-Gaussian fragment cluster inside the left box
    filled = fill_from_neighbours(points, labels, min_instance_fraction=0.01)
    assert len(np.unique(filled)) == 3
    assert (
        filled[inside_left] == filled[np.flatnonzero(truth == 0)[~np.isin(np.flatnonzero(truth == 0), inside_left)][0]]
    ).all()
    # without dissolution the fragment stays a fifth... fourth instance
    kept = fill_from_neighbours(points, labels, min_instance_fraction=0.0)
    assert len(np.unique(kept)) == 4


def test_cluster_levels_fill_is_reported_and_switchable():
    means, offsets, support, object_of, _ = two_level_scene()
    filled = cluster_levels(means, offsets, support, ("instance", "part"))
    plain = cluster_levels(means, offsets, support, ("instance", "part"), fill=False)
    assert filled.level(0).clustering["fill"] == "spatial"
    assert "fill" not in plain.level(0).clustering
    assert filled.level(0).num_noise <= plain.level(0).num_noise


def test_merge_joins_a_spread_object_and_keeps_converged_neighbours_apart():
    rng = np.random.default_rng(4)
    # a flat object's votes smeared along a 1.0-long bar, cut in three pieces; two converged
    # objects 0.2 apart (closer than the bar's pieces) with tight votes
    bar = np.concatenate(
        [
            np.column_stack([rng.uniform(lo, lo + 1 / 3, 300), rng.normal(0.0, 0.02, (300, 2))])
            for lo in (-0.5, -1 / 6, 1 / 6)
        ]
    )
    tight = np.concatenate([rng.normal(c, 0.01, size=(300, 3)) for c in ([3.0, 0.0, 0.0], [3.2, 0.0, 0.0])])
    votes = np.concatenate([bar, tight])
    labels = np.repeat([0, 1, 2, 3, 4], 300)
    for scale in (1.0, 50.0):  # the rule does not depend on the scene's units
        merged = merge_spread_clusters(votes * scale, labels, separation=2.5)
        assert len(set(merged[:900])) == 1
        assert len({merged[900], merged[1200], merged[0]}) == 3
    assert len(np.unique(merge_spread_clusters(votes, labels, separation=0.0))) == 5
