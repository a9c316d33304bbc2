"""The training-mask check of the instances (votesplat_ns/core/mask_consensus.py)."""

import math

import numpy as np
import torch

from votesplat_ns.core.cameras import PinholeView
from votesplat_ns.core.clustering import cluster_levels
from votesplat_ns.core.mask_consensus import (
    bisect_by_masks,
    drawn_masks,
    drop_unmasked,
    merge_agreeing,
    regroup_with_masks,
    seen_mask_table,
    seen_pixels,
    split_deviants,
)
from votesplat_ns.core.mask_sightings import sitting_masks
from votesplat_ns.core.rasterize_torch import rasterize_torch

VIEWS = 6


def blob(centre, count, spread=0.05, seed=0):
    return np.random.default_rng(seed).normal(centre, spread, size=(count, 3))


def table_from(masks_per_point, views=VIEWS):
    """[V, N] table where every point is seen in every view in the given mask id."""
    return np.tile(np.asarray(masks_per_point, dtype=np.int32), (views, 1))


def test_sitting_masks_needs_a_majority_and_enough_seen():
    table = np.array([[1, 1, 1, 2, -1], [1, 2, 3, 0, -1], [0, 0, 0, 1, -1], [-1, -1, -1, -1, 1]], dtype=np.int32)
    members = np.arange(5)
    assert sitting_masks(table, members, min_share=0.5, min_seen=3).tolist() == [1, -1, 0, -1]


def test_split_moves_an_object_resting_in_another_out_of_its_cluster():
    # a bowl and the fruit in it voted for one centre: one cluster; the masks keep them apart
    bowl, fruit = blob([0, 0, 0], 400, 0.3), blob([0, 0, 0.1], 60, 0.05, seed=1)
    means = np.concatenate([bowl, fruit])
    labels = np.zeros(len(means), dtype=np.int64)
    table = table_from([1] * 400 + [2] * 60)
    table[0, 400:] = 1  # one view where the fruit's mask is merged with the bowl's
    out = split_deviants(labels, means, table, radius=0.2, min_size=10)
    assert np.unique(out[:400]).tolist() == [0]
    assert np.unique(out[400:]).size == 1 and out[400] != 0
    # too small a group stays where it was
    assert (split_deviants(labels, means, table, radius=0.2, min_size=61) == 0).all()


def _two_boxes_in_one_cluster(views=8, count=300):
    """Two boxes of one size that voted into one cluster; each view shows one of them whole and 40% of the other,
    so the cluster's mask is one box's in half of the views and the other's in the rest."""
    rng = np.random.default_rng(3)
    means = np.concatenate([blob([0, 0, 0], count, 0.2), blob([1, 0, 0], count, 0.2, seed=1)])
    table = np.full((views, 2 * count), -1, dtype=np.int32)
    for v in range(views):
        a, b = 1 + v % 3, 5  # mask ids change from view to view
        front, back = (slice(0, count), slice(count, None)) if v % 2 == 0 else (slice(count, None), slice(0, count))
        table[v, front] = a if v % 2 == 0 else b
        glimpsed = rng.random(count) < 0.4
        table[v, back] = np.where(glimpsed, b if v % 2 == 0 else a, -1)
    return means, np.zeros(2 * count, dtype=np.int64), table


def test_bisect_cuts_two_objects_of_one_size_that_the_deviants_miss():
    means, labels, table = _two_boxes_in_one_cluster()
    table[3] = 7  # a view whose mask merges the two (a mask error)
    # neither box's members lie away from the cluster's mask in most of their views
    assert (split_deviants(labels, means, table, radius=0.3, min_size=5) == 0).all()
    out = bisect_by_masks(labels, means, table, min_size=5)
    assert np.unique(out[:300]).size == 1 and np.unique(out[300:]).size == 1 and out[0] != out[300]
    # regroup_with_masks takes it (bisect=True) and the merge that follows keeps the cut
    regrouped, stats = regroup_with_masks(labels, means, table, bisect=True, objects=False)
    assert stats["num_clusters"] == 2 and regrouped[0] != regrouped[300]


def test_bisect_cuts_again_where_a_side_still_holds_two_objects():
    # three boxes of one size in one cluster; each view shows one whole and glimpses the other two
    rng = np.random.default_rng(5)
    count, views = 200, 9
    means = np.concatenate([blob([2.0 * b, 0, 0], count, 0.2, seed=b) for b in range(3)])
    table = np.full((views, 3 * count), -1, dtype=np.int32)
    for v in range(views):
        for b in range(3):
            box = slice(b * count, (b + 1) * count)
            mask = 1 + (b + v) % 3  # mask ids change from view to view
            glimpsed = rng.random(count) < (1.0 if b == v % 3 else 0.4)
            table[v, box] = np.where(glimpsed, mask, -1)
    labels = np.zeros(3 * count, dtype=np.int64)
    out = bisect_by_masks(labels, means, table, min_size=5)
    assert np.unique(out).size >= 3  # a cut in two leaves a side with two boxes, which is cut again
    # a cut may leave a third box's pieces on both sides; the merge after it joins them again (one mask per view)
    out, stats = regroup_with_masks(labels, means, table, objects=False)
    boxes = [np.unique(out[b * count : (b + 1) * count]) for b in range(3)]
    assert stats["num_clusters"] == 3 and all(ids.size == 1 for ids in boxes)
    assert len({int(ids[0]) for ids in boxes}) == 3


def test_bisect_keeps_one_object_whose_mask_one_view_splits():
    means = blob([0, 0, 0], 400, 0.3)
    labels = np.zeros(400, dtype=np.int64)
    table = table_from([2] * 400, views=8)
    table[5, means[:, 0] > 0] = 3  # a mask error: the object in two masks in one view
    assert (bisect_by_masks(labels, means, table, min_size=5) == 0).all()


def test_merge_joins_pieces_that_share_masks_and_keeps_neighbours_apart():
    labels = np.array([0] * 50 + [1] * 50 + [2] * 50)
    # clusters 0 and 1 lie in the same mask in every view (one object cut in two); 2 is another object
    table = table_from([3] * 100 + [4] * 50)
    merged, merges = merge_agreeing(labels, table, min_agreement=0.5, min_views=3)
    assert merges == 1
    assert len(np.unique(merged[:100])) == 1 and merged[0] != merged[120]
    # evidence from fewer views than min_views merges nothing
    few = np.full_like(table, -1)
    few[:2] = table[:2]
    assert merge_agreeing(labels, few, min_views=3)[1] == 0


def test_merge_needs_most_views_to_agree():
    labels = np.array([0] * 20 + [1] * 20)
    table = table_from([1] * 40)
    table[:4, 20:] = 2  # 4 of 6 views keep them apart
    assert merge_agreeing(labels, table, min_agreement=0.5)[1] == 0
    table[:2, 20:] = 1  # now 4 of 6 agree
    assert merge_agreeing(labels, table, min_agreement=0.5)[1] == 1


def test_drop_removes_clusters_outside_every_mask():
    labels = np.array([0] * 20 + [1] * 20 + [-1] * 5)
    table = table_from([1] * 20 + [0] * 20 + [1] * 5)
    out = drop_unmasked(labels, table)
    assert (out[:20] == 0).all() and (out[20:] == -1).all()


def test_seen_pixels_keeps_what_the_render_hides_out():
    # two opaque blobs on the optical axis: the near one hides the far one
    near, far = blob([0, 0, 2.0], 200, 0.05), blob([0, 0, 4.0], 200, 0.05, seed=1)
    side = blob([1.5, 0, 4.0], 200, 0.05, seed=2)  # visible beside them
    means = torch.tensor(np.concatenate([near, far, side]), dtype=torch.float32)
    n = means.shape[0]
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1)
    scales = torch.full((n, 3), 0.06)
    opacities = torch.full((n,), 0.99)
    K = torch.tensor([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    view = PinholeView(torch.eye(4), K, 64, 48)

    def rasterize(*args, **kwargs):
        return rasterize_torch(*args, **kwargs)

    pixels = seen_pixels(rasterize, means, quats, scales, opacities, view)
    seen = pixels >= 0
    assert seen[:200].mean() > 0.15  # the front of the near blob (centres deeper inside it are hidden)
    assert seen[200:400].mean() < 0.02
    assert seen[400:].mean() > 0.15
    # the table puts each seen centre in the mask under it; unseen ones are -1
    masks = np.full((48, 64), 7, dtype=np.int64)
    table = seen_mask_table([pixels], [masks])
    assert table.shape == (1, n) and (table[0][seen] == 7).all() and (table[0][~seen] == -1).all()
    # the pixel of a seen centre is where it projects
    i = int(np.flatnonzero(seen[400:])[0]) + 400
    x, y, z = means[i].tolist()
    assert pixels[i] == math.floor(y / z * 60 + 24) * 64 + math.floor(x / z * 60 + 32)


def test_drawn_masks_follow_the_blending_weights():
    # a fruit-like blob hidden behind a nearer wall, the wall, and a blob beside them; the left
    # half of the image is mask 1, the right half mask 2 (a blob beside the wall lies in mask 2)
    wall = blob([-0.3, 0, 2.0], 200, 0.05)
    hidden = blob([-0.3, 0, 2.3], 200, 0.05, seed=1)
    side = blob([1.2, 0, 4.0], 200, 0.05, seed=2)
    faint = blob([1.2, 0.6, 4.0], 20, 0.01, seed=3)  # tiny and nearly transparent
    means = torch.tensor(np.concatenate([wall, hidden, side, faint]), dtype=torch.float32)
    n = means.shape[0]
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1)
    scales = torch.full((n, 3), 0.06)
    scales[600:] = 0.003
    opacities = torch.full((n,), 0.99)
    opacities[600:] = 0.02
    K = torch.tensor([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    view = PinholeView(torch.eye(4), K, 64, 48)
    labels = np.ones((48, 64), dtype=np.int64)
    labels[:, 32:] = 2
    drawn = drawn_masks(rasterize_torch, means, quats, scales, opacities, view, labels, chunk=1)
    assert drawn.shape == (n,) and drawn.dtype == np.int32
    # the wall's front Gaussians are drawn into mask 1 (those deeper inside it are hidden)
    assert (drawn[:200] == 1).mean() > 0.15 and (drawn[:200] == 2).sum() == 0
    assert (drawn[200:400] == -1).mean() > 0.95  # hidden behind it: undecided, not the wall's mask
    assert (drawn[400:600] == 2).mean() > 0.1 and (drawn[400:600] == 1).sum() == 0
    assert (drawn[600:] == -1).all()  # under half a pixel of weight
    # the per-mask sums do not depend on how the masks are chunked into renders
    assert np.array_equal(drawn, drawn_masks(rasterize_torch, means, quats, scales, opacities, view, labels))
    # a Gaussian straddling the two masks (about 60% of it right of the border) is decided only
    # when the share asked for is below its larger share
    straddle = torch.tensor([[0.03, 0.0, 4.0]])
    args = (rasterize_torch, straddle, quats[:1], torch.full((1, 3), 0.3), torch.full((1,), 0.99), view, labels)
    assert drawn_masks(*args).tolist() == [2]
    assert drawn_masks(*args, min_share=0.7).tolist() == [-1]


def test_regroup_end_to_end_on_the_mask_table():
    # cluster 0: an object over-split by the votes into 0 and 1; cluster 2 holds two objects; 3: a floater
    a0, a1 = blob([0, 0, 0], 100), blob([0.3, 0, 0], 100, seed=1)
    b, c = blob([3, 0, 0], 100, seed=2), blob([3.2, 0.2, 0], 40, seed=3)
    floater = blob([6, 0, 0], 30, seed=4)
    means = np.concatenate([a0, a1, b, c, floater])
    labels = np.array([0] * 100 + [1] * 100 + [2] * 140 + [3] * 30)
    table = table_from([1] * 200 + [2] * 100 + [5] * 40 + [0] * 30)
    out, stats = regroup_with_masks(labels, means, table, min_size=10)
    assert len(np.unique(out[:200])) == 1
    assert len(np.unique(out[200:300])) == 1 and len(np.unique(out[300:340])) == 1 and out[200] != out[300]
    assert (out[340:] == -1).all()
    assert stats["num_clusters"] == 3 and stats["merges"] == 1
    assert sorted(np.unique(out[out >= 0]).tolist()) == [0, 1, 2]


def test_cluster_levels_applies_the_refinement_per_level():
    means = np.concatenate([blob([0, 0, 0], 300), blob([5, 0, 0], 300, seed=1)])
    offsets = np.zeros((600, 2, 3))
    offsets[:300, :, :] = -means[:300, None, :]  # votes converge per object
    offsets[300:, :, :] = np.array([5.0, 0, 0]) - means[300:, None, :]
    support = np.ones((600, 2))
    calls = []

    def refine(index, name, ids):
        calls.append((index, name, int(ids.max()) + 1))
        return np.zeros_like(ids), {"merges": 1}

    result = cluster_levels(means, offsets, support, ("instance", "part"), refine=refine)
    assert calls == [(0, "instance", 2), (1, "part", 2)]
    assert result.level("instance").num_instances == 1
    assert result.level("part").clustering["mask_check"] == {"merges": 1}
