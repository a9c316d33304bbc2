"""Whole objects after the mask check (core/whole_objects.py), on constructed point sets and mask tables.

A mask table [V, N] says per view where each Gaussian's centre is seen: -1 not seen, 0 in no mask,
k >= 1 in mask k. The scenes are grids of points at spacing 0.1 standing in for Gaussians.
"""

from __future__ import annotations

import numpy as np

from votesplat_ns.core.clustering import typical_spacing
from votesplat_ns.core.mask_consensus import regroup_with_masks
from votesplat_ns.core.whole_objects import whole_objects

STEP = 0.1


def box_surface(low, high, step: float = STEP, bottom: bool = True) -> np.ndarray:
    """Grid points on the faces of the box [low, high] (without the bottom face when ``bottom`` is False)."""
    low, high = np.asarray(low, float), np.asarray(high, float)
    axes = [np.arange(lo, hi + step / 2, step) for lo, hi in zip(low, high)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    on_face = (np.isclose(grid, low) | np.isclose(grid, high)).any(axis=1)
    if not bottom:
        on_face &= ~(
            np.isclose(grid[:, 2], low[2])
            & ~(np.isclose(grid[:, :2], low[:2]) | np.isclose(grid[:, :2], high[:2])).any(axis=1)
        )
    return grid[on_face]


def box_interior(low, high, step: float = STEP) -> np.ndarray:
    """Grid points strictly inside the box, offset half a step from the surface grid."""
    axes = [np.arange(lo + 1.5 * step, hi - step, step) for lo, hi in zip(low, high)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


class Scene:
    """Points with labels and a mask table built object by object."""

    def __init__(self, views: int = 6) -> None:
        self.points: list = []
        self.labels: list = []
        self.rows: list = []
        self.views = views

    def add(self, points: np.ndarray, label: int, masks) -> np.ndarray:
        """Add ``points`` with ``label``; ``masks``: one mask id per view (-1 unseen, 0 no mask) for all of them."""
        start = sum(len(p) for p in self.points)
        self.points.append(np.asarray(points, float))
        self.labels.append(np.full(len(points), label, dtype=np.int64))
        self.rows.append(np.repeat(np.asarray(masks, dtype=np.int32)[:, None], len(points), axis=1))
        return np.arange(start, start + len(points))

    def build(self):
        means = np.concatenate(self.points)
        labels = np.concatenate(self.labels)
        table = np.concatenate(self.rows, axis=1)
        return means, labels, table


def run(means, labels, table, **options):
    spacing = typical_spacing(means[labels >= 0])
    out, confidence, stats = whole_objects(labels, means, table, spacing, **options)
    return out, confidence, stats


def test_fragment_touching_its_object_with_agreeing_masks_joins() -> None:
    scene = Scene()
    body = scene.add(box_surface([0, 0, 0], [1, 1, 1]), 0, [1, 1, 2, 2, 3, -1])
    # a fragment on the object's side (within a spacing of it), seen in the object's masks
    fragment = scene.add(box_surface([1.1, 0.4, 0.4], [1.2, 0.6, 0.6]), 1, [1, 1, 2, 2, -1, -1])
    out, confidence, stats = run(*scene.build())
    assert out[fragment[0]] == out[body[0]] and (out[fragment] == out[fragment[0]]).all()
    assert stats["join"]["joined"] == 1 and stats["num_instances"] == 1
    assert confidence.shape == (1,) and confidence[0] > 0.5


def test_contact_alone_never_joins() -> None:
    scene = Scene()
    scene.add(box_surface([0, 0, 0], [1, 1, 1]), 0, [1, 1, 2, 2, 3, -1])
    # touching, seen in two views, in masks of its own there
    fragment = scene.add(box_surface([1.1, 0.4, 0.4], [1.2, 0.6, 0.6]), 1, [4, -1, 5, -1, -1, -1])
    out, _, stats = run(*scene.build())
    assert stats["join"]["joined"] == 0 and stats["join"]["refused_by_masks"] == 1
    assert (out[fragment] >= 0).all() and len(set(out[out >= 0])) == 2


def test_instance_no_view_sees_dissolves_into_the_object_it_lies_in() -> None:
    scene = Scene()
    cube = scene.add(box_surface([0, 0, 0], [2, 2, 2]), 0, [1, 1, 2, 2, 3, 3])
    # a cluster of Gaussians hidden inside the cube in every view (they voted, so the vote
    # clustering made an instance of them), and one behind it, in no view either: within contact
    # (3 spacings) of the cube, beyond the hidden rule's reach (1.5 spacings)
    inner = scene.add(box_interior([0, 0, 0], [2, 2, 2])[::7], 1, [-1] * 6)
    behind = scene.add(box_surface([2.25, 0.8, 0.8], [2.45, 1.2, 1.2]), 2, [-1] * 6)
    # seen in one view only: too little evidence to stand as an instance
    glimpsed = scene.add(box_surface([-0.3, 0.8, 0.8], [-0.1, 1.2, 1.2]), 3, [4, -1, -1, -1, -1, -1])
    means, labels, table = scene.build()
    out, _, stats = run(means, labels, table)
    assert (out[cube] == 0).all() and (out[inner] == 0).all()
    assert (out[behind] == -1).all() and (out[glimpsed] == -1).all()
    assert stats["floaters"]["floaters"] == 3 and stats["num_instances"] == 1
    # switched off, an unseen instance that touches another one is kept (contact as its only evidence), unless it
    # lies inside another instance's hull: the rehome rule then moves its Gaussians there
    kept, _, _ = run(means, labels, table, unseen=False, rehome=False)
    assert len(set(kept[kept >= 0])) == 4
    rehomed, _, stats = run(means, labels, table, unseen=False)
    assert (rehomed[inner] == rehomed[cube[0]]).all() and stats["rehome"]["rehomed"] == len(inner)
    assert len(set(rehomed[rehomed >= 0])) == 3


def test_instance_that_views_show_only_a_few_members_of_becomes_background() -> None:
    scene = Scene()
    cube = scene.add(box_surface([0, 0, 0], [1, 1, 1]), 0, [1, 1, 2, 2, 3, 3])
    # a cluster of 98 Gaussians, away from the cube, of which three views each see two members in a mask: no
    # view shows enough of it (min_seen, 5 members) to make it an object a user could find
    glimpsed = scene.add(box_surface([3, 0, 0], [3.3, 0.3, 0.3]), 1, [-1] * 6)
    # a small object of 6 Gaussians seen whole in four views, and one of 3 seen whole in two: views show them
    small = scene.add(box_surface([5, 0, 0], [5.1, 0.1, 0.1])[:6], 2, [5, 5, 6, 6, -1, -1])
    tiny = scene.add(np.array([[7.0, 0, 0], [7.1, 0, 0], [7.0, 0.1, 0]]), 3, [7, 8, -1, -1, -1, -1])
    means, labels, table = scene.build()
    for view in range(3):
        table[view, glimpsed[2 * view : 2 * view + 2]] = 4
    out, _, stats = run(means, labels, table)
    assert (out[glimpsed] == -1).all() and stats["floaters"]["floaters"] == 1
    assert len({out[cube[0]], out[small[0]], out[tiny[0]]}) == 3 and stats["num_instances"] == 3
    # counting a view that sees any member, three views see it in a mask: it stays an instance
    kept, _, _ = run(means, labels, table, unseen_min_seen=False)
    assert (kept[glimpsed] >= 0).all() and len(set(kept[kept >= 0])) == 4


def test_small_object_with_its_own_masks_stays_apart() -> None:
    scene = Scene()
    bowl = scene.add(box_surface([0, 0, 0], [1.5, 1.5, 0.6]), 0, [1, 1, 2, 2, 3, 3])
    # a fruit of a few dozen Gaussians resting on it, in masks of its own where views see it
    fruit = scene.add(box_surface([0.5, 0.5, 0.7], [0.8, 0.8, 0.9]), 1, [4, 4, 5, 5, -1, 0])
    out, _, stats = run(*scene.build())
    assert out[fruit[0]] != out[bowl[0]] and (out[fruit] == out[fruit[0]]).all()
    assert stats["join"]["joined"] == 0 and stats["join"]["refused_by_masks"] == 1


def test_a_fragment_in_the_other_half_of_a_split_mask_joins_the_object_that_holds_the_mask() -> None:
    scene = Scene()
    body = scene.add(box_surface([0, 0, 0], [1, 1, 1]), 1, [1, 1, 1, 2, 3, -1])
    # a fragment on the object's side, seen in three views
    fragment = scene.add(box_surface([1.1, 0.4, 0.4], [1.2, 0.6, 0.6]), 2, [1, 1, 1, -1, -1, -1])
    # a fruit resting on the object: its own mask in two views, merged into the object's in two others
    fruit = scene.add(box_surface([0.3, 0.3, 1.1], [0.5, 0.5, 1.2]), 3, [6, 7, 2, 2, -1, 0])
    # an object apart, in the views' highest mask ids
    shelf = scene.add(box_surface([3, 0, 0], [4, 1, 1]), 0, [9, 9, 9, 4, 4, -1])
    means, labels, table = scene.build()
    # in those three views the masks split the object in two, and the fragment lies in the smaller half
    side = body[means[body, 0] > 0.75]
    table[:3, side] = 5
    table[:3, fragment] = 5
    out, _, stats = run(means, labels, table)
    assert 2 * len(side) < len(body)  # the object sits in mask 1: the fragment agrees with it in none of its views
    assert stats["join"]["joined"] == 0
    assert (out[fragment] == out[body[0]]).all() and stats["orphans"] == {"adopted": 1, "adopted_gaussians": 18}
    assert out[fruit[0]] != out[body[0]] and stats["num_instances"] == 3 and len(set(out[shelf])) == 1
    kept, _, stats = run(means, labels, table, orphans=False)
    assert len(set(kept[kept >= 0])) == 4 and "orphans" not in stats


def test_a_small_object_whose_masks_hold_more_of_its_container_behind_it_is_not_adopted() -> None:
    scene = Scene()
    bowl = scene.add(box_surface([0, 0, 0], [1.5, 1.5, 0.6]), 0, [1, 1, 2, 2, 3, 3])
    # a fruit that two views show, in a mask of its own that also holds the bowl's Gaussians just behind it (the
    # centre test's depth tolerance): more of them than of the fruit, so the fruit is never most of its mask
    fruit = scene.add(box_surface([0.5, 0.5, 0.7], [0.7, 0.7, 0.8]), 1, [4, 4, -1, -1, -1, -1])
    means, labels, table = scene.build()
    behind = bowl[(np.abs(means[bowl, :2] - 0.6) <= 0.2 + 1e-9).all(axis=1) & np.isclose(means[bowl, 2], 0.6)]
    table[:2, behind] = 4
    assert len(behind) > len(fruit) and 10 * len(behind) < len(bowl)
    out, _, stats = run(means, labels, table)
    assert out[fruit[0]] != out[bowl[0]] and stats["orphans"]["adopted"] == 0
    # the mask holds most of it from the bowl, but a small piece of the bowl: counted as the bowl's, it is adopted
    adopted, _, stats = run(means, labels, table, orphan_cover=0.0)
    assert (adopted[fruit] == adopted[bowl[0]]).all() and stats["orphans"]["adopted"] == 1


def test_the_container_gaussians_at_a_small_objects_contact_that_its_masks_see_move_to_it() -> None:
    scene = Scene()
    bowl = scene.add(box_surface([0, 0, 0], [1.5, 1.5, 0.6]), 0, [1, 1, 2, 2, 3, 3])
    fruit = scene.add(box_surface([0.5, 0.5, 0.7], [0.8, 0.8, 0.9]), 1, [4, 4, 5, 5, -1, 0])
    # the bowl's instance holds Gaussians under the fruit, at the contact (within the fruit's box grown by the
    # reach): seen in the fruit's masks in 2 views against 4 in the bowl's, they move; seen there in 1 view, they stay
    grid = np.stack(np.meshgrid([0.55, 0.65, 0.75], [0.55, 0.65, 0.75], indexing="ij"), -1).reshape(-1, 2)
    at_contact = np.column_stack([grid, np.full(len(grid), 0.65)])
    moving = scene.add(at_contact, 0, [4, 1, 5, 2, 3, 3])
    staying = scene.add(at_contact + [0, 0, -0.02], 0, [4, 1, 2, 2, 3, 3])
    # beyond the fruit's box the fruit's masks do not take a Gaussian of the bowl
    far = scene.add(at_contact + [0.6, 0.6, 0], 0, [4, 4, 5, 5, 3, 3])
    means, labels, table = scene.build()
    out, _, stats = run(means, labels, table)  # on by default
    assert (out[moving] == out[fruit[0]]).all() and out[fruit[0]] != out[bowl[0]]
    assert (out[staying] == out[bowl[0]]).all() and (out[far] == out[bowl[0]]).all()
    assert stats["contact"] == {"contact_gaussians": len(moving), "contact_sources": 1}
    kept, _, kept_stats = run(means, labels, table, contact=False)
    assert (kept[moving] == kept[bowl[0]]).all() and "contact" not in kept_stats
    # two touching objects of one size (stacked cubes) are neither's container
    same = Scene()
    lower = same.add(box_surface([0, 0, 0], [1, 1, 1]), 0, [1, 1, 2, 2, 3, 3])
    upper = same.add(box_surface([0, 0, 1.1], [1, 1, 2.1]), 1, [4, 4, 5, 5, 6, 6])
    touching = same.add(np.array([[0.5, 0.5, 1.0], [0.4, 0.5, 1.0]]), 0, [4, 1, 5, 2, 6, 3])
    out, _, stats = run(*same.build())
    assert out[lower[0]] != out[upper[0]] and (out[touching] == out[lower[0]]).all()


def test_gaussians_that_the_masks_show_on_a_touching_instance_settle_in_it() -> None:
    scene = Scene()
    left = scene.add(box_surface([0, 0, 0], [1, 1, 1]), 0, [1, 1, 2, 2, 3, 3])
    right = scene.add(box_surface([1.1, 0, 0], [2.1, 1, 1]), 1, [4, 4, 5, 5, 6, 6])
    # the left cube's instance holds a patch of the right cube's near face: the views show it in the right
    # cube's masks in four of the five views that see it; a patch the views show half in each stays where it is
    patch = np.array([[1.1, y, z] for y in (0.4, 0.5, 0.6) for z in (0.4, 0.5, 0.6)])
    misplaced = scene.add(patch + [0.01, 0, 0], 0, [4, 4, 5, 5, 3, -1])
    split = scene.add(patch + [0.01, 0, 0.3], 0, [4, 1, 5, 2, 3, 6])
    # background by the right cube: seen in its masks in two views settles in it; seen there in one view it is
    # not this rule's (the hidden rule's reach in the masks takes it)
    fringe = scene.add(patch + [1.05, 0, 0], -1, [4, -1, 5, -1, -1, -1])
    glimpsed = scene.add(patch + [1.05, 0, 0.3], -1, [4, -1, -1, -1, -1, -1])
    # a small instance that the masks show on the right cube moves only as a whole, by the join or orphans rule
    small = scene.add(patch + [0.5, 0, 0.55], 2, [4, 4, 5, 5, 6, 6])
    means, labels, table = scene.build()
    out, _, stats = run(means, labels, table, join=False, orphans=False)
    assert (out[misplaced] == out[right[0]]).all() and (out[split] == out[left[0]]).all()
    assert (out[fringe] == out[right[0]]).all() and (out[glimpsed] == out[right[0]]).all()  # the latter by the reach
    assert len(np.unique(out[small])) == 1 and out[small[0]] not in (out[left[0]], out[right[0]])
    assert stats["settle"] == {"settled": len(misplaced) + len(fringe), "settled_from_background": len(fringe)}
    off, _, stats = run(means, labels, table, join=False, orphans=False, settle=False)
    assert (off[misplaced] == off[left[0]]).all() and "settle" not in stats
    # 4 of 5 views is below 0.9
    stricter, _, _ = run(means, labels, table, join=False, orphans=False, settle_agreement=0.9)
    assert (stricter[misplaced] == stricter[left[0]]).all()


def test_stacked_cubes_stay_apart() -> None:
    scene = Scene()
    lower = scene.add(box_surface([0, 0, 0], [1, 1, 1]), 0, [1, 1, 2, 2, 3, 3])
    upper = scene.add(box_surface([0, 0, 1.1], [1, 1, 2.1]), 1, [4, 4, 5, 5, 6, 6])
    # a small cube between two larger ones, seen in two views only, in its own masks
    middle = scene.add(box_surface([1.1, 0.3, 0.3], [1.4, 0.6, 0.6]), 2, [7, -1, 8, -1, -1, -1])
    out, _, stats = run(*scene.build())
    assert len({int(out[lower[0]]), int(out[upper[0]]), int(out[middle[0]])}) == 3
    assert stats["join"]["joined"] == 0


def test_hidden_gaussian_inside_an_object_joins_it_and_the_table_under_it_does_not() -> None:
    scene = Scene()
    cube = scene.add(box_surface([0, 0, 0], [1, 1, 1], bottom=False), 0, [1, 1, 2, 2, 3, 3])
    inside = scene.add(box_interior([0, 0, 0], [1, 1, 1]), -1, [-1] * 6)
    # the table: seen in no mask around the cube, never seen under it; at the height of the cube's
    # lowest visible Gaussians, so only the hull's margin keeps it out
    xy = np.stack(np.meshgrid(np.arange(-1, 2.01, STEP), np.arange(-1, 2.01, STEP), indexing="ij"), -1).reshape(-1, 2)
    table_points = np.column_stack([xy, np.zeros(len(xy))])
    under = ((xy >= -1e-9) & (xy <= 1 + 1e-9)).all(axis=1)
    table_seen = scene.add(table_points[~under], -1, [0, 0, 0, 0, 0, 0])
    table_under = scene.add(table_points[under], -1, [-1] * 6)
    means, labels, table = scene.build()
    out, _, stats = run(means, labels, table)
    assert (out[inside] == out[cube[0]]).all()
    assert (out[table_under] == -1).all() and (out[table_seen] == -1).all()
    assert stats["hidden"]["hidden_taken"] >= len(inside)
    # switched off, the interior stays background
    off, _, _ = run(means, labels, table, hidden=False)
    assert (off[inside] == -1).all()


def test_unseen_fuzz_within_reach_of_an_object_joins_it_and_farther_stays_background() -> None:
    scene = Scene()
    cube = scene.add(box_surface([0, 0, 0], [1, 1, 1]), 0, [1, 1, 2, 2, 3, 3])
    # no view sees these: a layer a spacing off the cube's side (its fuzz, outside the hull of the cube's
    # Gaussians), and one three spacings off the opposite side (beyond the reach of 1.5 spacings)
    fuzz = scene.add(box_surface([1.1, 0.2, 0.2], [1.1, 0.8, 0.8]), -1, [-1] * 6)
    far = scene.add(box_surface([-0.3, 0.2, 0.2], [-0.3, 0.8, 0.8]), -1, [-1] * 6)
    # a spacing above the middle of the top, but one view saw it outside every mask: settled background
    above = scene.add(box_surface([0.4, 0.4, 1.1], [0.6, 0.6, 1.1]), -1, [0, -1, -1, -1, -1, -1])
    means, labels, table = scene.build()
    out, _, stats = run(means, labels, table)
    assert (out[fuzz] == out[cube[0]]).all()
    assert (out[far] == -1).all() and (out[above] == -1).all()
    assert stats["hidden"]["hidden_reached"] == len(fuzz)
    # without the reach only the hull counts: the fuzz stays background
    hull_only, _, stats = run(means, labels, table, hidden_reach=0.0)
    assert (hull_only[fuzz] == -1).all() and stats["hidden"]["hidden_reached"] == 0
    # a neighbour of the fuzz seen as background (settled, not of the cube) keeps it out
    table[0, far] = 0
    moved = means.copy()
    moved[far, 0] = 1.2  # the seen layer right behind the fuzz
    mixed, _, _ = run(moved, labels, table)
    assert (mixed[fuzz] == -1).any()


def test_fringe_seen_in_an_object_s_masks_within_reach_joins_it_next_to_seen_background() -> None:
    scene = Scene()
    cube = scene.add(box_surface([0, 0, 0], [1, 1, 1]), 0, [1, 1, 2, 2, 3, 3])
    # a layer a spacing off the cube's side, left out by the clustering, that views see in the cube's masks;
    # two spacings behind it, within the contact distance, background that views see outside every mask (an
    # unseen layer there would stay out)
    fringe = scene.add(box_surface([1.1, 0.3, 0.3], [1.1, 0.7, 0.7]), -1, [1, -1, 2, -1, -1, -1])
    behind = scene.add(box_surface([1.3, 0.0, 0.0], [1.3, 1.0, 1.0]), -1, [0, 0, 0, -1, -1, -1])
    # the same a spacing off the opposite side, seen in another object's mask
    other = scene.add(box_surface([-0.1, 0.3, 0.3], [-0.1, 0.7, 0.7]), -1, [9, -1, 9, -1, -1, -1])
    means, labels, table = scene.build()
    out, _, stats = run(means, labels, table)
    assert (out[fringe] == out[cube[0]]).all()
    assert (out[behind] == -1).all() and (out[other] == -1).all()
    assert stats["settle"] == {"settled": len(fringe), "settled_from_background": len(fringe)}  # the settle rule first
    out, _, stats = run(means, labels, table, settle=False)
    assert (out[fringe] == out[cube[0]]).all() and stats["hidden"]["reached_in_masks"] == len(fringe)
    # switched off (and the settle rule, which takes the fringe by its masks too), only Gaussians no view sees
    # are reached: the fringe stays background, and so would an unseen fringe there, too near the seen background
    off, _, stats = run(means, labels, table, reach_in_masks=False, settle=False)
    assert (off[fringe] == -1).all() and stats["hidden"]["reached_in_masks"] == 0
    table[:, fringe] = -1
    unseen, _, _ = run(means, labels, table)
    assert (unseen[fringe] == -1).all()


def test_background_seen_outside_every_mask_stays_background() -> None:
    scene = Scene()
    cube = scene.add(box_surface([0, 0, 0], [1, 1, 1]), 0, [1, 1, 2, 2, 3, 3])
    # inside the cube's hull, but views see it in no mask (a background Gaussian the centre test saw)
    seen = scene.add(box_interior([0, 0, 0], [1, 1, 1])[:5], -1, [0, 0, 0, -1, -1, -1])
    out, _, stats = run(*scene.build())
    assert (out[seen] == -1).all() and (out[cube] == 0).all()
    assert stats["hidden"]["seen_background"] == 5


def test_floater_becomes_background() -> None:
    scene = Scene()
    cube = scene.add(box_surface([0, 0, 0], [1, 1, 1]), 0, [1, 1, 2, 2, 3, 3])
    seen_outside = scene.add(box_surface([3, 3, 3], [3.2, 3.2, 3.2]), 1, [0, 0, 0, -1, -1, -1])
    never_seen = scene.add(box_surface([-3, 3, 3], [-2.8, 3.2, 3.2]), 2, [-1] * 6)
    out, _, stats = run(*scene.build())
    assert (out[seen_outside] == -1).all() and (out[never_seen] == -1).all() and (out[cube] == 0).all()
    assert stats["floaters"]["floaters"] == 2
    kept, _, _ = run(*scene.build(), floaters=False)
    assert len(set(kept[kept >= 0])) == 3


def test_regroup_with_masks_runs_the_rules_and_reports_confidence() -> None:
    scene = Scene()
    body = scene.add(box_surface([0, 0, 0], [1, 1, 1]), 0, [1, 1, 2, 2, 3, -1])
    fragment = scene.add(box_surface([1.1, 0.4, 0.4], [1.2, 0.6, 0.6]), 1, [1, 1, 2, 2, -1, -1])
    means, labels, table = scene.build()
    # the fragment has too few Gaussians seen per view for the check's own merge (min_seen)
    before, stats_before = regroup_with_masks(labels, means, table, min_seen=20, objects=False)
    assert len(set(before[before >= 0])) == 2 and "confidence" not in stats_before
    out, stats = regroup_with_masks(labels, means, table, min_seen=20)
    assert out[fragment[0]] == out[body[0]]
    assert stats["objects"]["join"]["joined"] == 1 and stats["confidence"].shape == (1,)
    off, _ = regroup_with_masks(labels, means, table, min_seen=20, join=False)
    assert len(set(off[off >= 0])) == 2


def test_level_confidence_travels_through_the_manifest(tmp_path) -> None:
    from votesplat_ns.core.instances import InstanceSet, LevelInstances

    means = np.arange(12, dtype=float).reshape(4, 3)
    ids = np.array([0, 0, 1, -1])
    level = LevelInstances.from_ids("instance", ids, ids >= 0, means, means, confidence=np.array([0.9, 0.25]))
    entries = level.to_manifest()["instances"]
    assert isinstance(entries, list) and entries[1]["confidence"] == 0.25
    InstanceSet(levels=[level], num_gaussians=4).save(tmp_path)
    loaded = InstanceSet.load(tmp_path).levels[0]
    assert loaded.confidence is not None and np.allclose(loaded.confidence, [0.9, 0.25])
    plain = LevelInstances.from_ids("instance", ids, ids >= 0, means, means)
    (tmp_path / "plain").mkdir()
    InstanceSet(levels=[plain], num_gaussians=4).save(tmp_path / "plain")
    assert InstanceSet.load(tmp_path / "plain").levels[0].confidence is None


def test_vote_proximity_is_an_optional_extra_condition() -> None:
    scene = Scene()
    body = scene.add(box_surface([0, 0, 0], [1, 1, 1]), 0, [1, 1, 2, 2, 3, -1])
    fragment = scene.add(box_surface([1.1, 0.4, 0.4], [1.2, 0.6, 0.6]), 1, [1, 1, 2, 2, -1, -1])
    means, labels, table = scene.build()
    rng = np.random.default_rng(0)
    votes = np.empty_like(means)
    votes[body] = [0.5, 0.5, 0.5] + rng.normal(0, 0.05, (len(body), 3))
    votes[fragment] = [3.0, 0.5, 0.5]  # voted far from the body's centre
    # (the orphans rule, which reads no votes, off: the body holds every mask the fragment sits in)
    far, _, stats = run(means, labels, table, votes=votes, join_vote_factor=2.0, orphans=False)
    assert far[fragment[0]] != far[body[0]] and stats["join"]["refused_by_votes"] == 1
    votes[fragment] = [0.55, 0.5, 0.5]
    near, _, _ = run(means, labels, table, votes=votes, join_vote_factor=2.0)
    assert near[fragment[0]] == near[body[0]]


def test_vote_centre_leaves_out_members_without_a_vote() -> None:
    from votesplat_ns.core.instances import LevelInstances

    means = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [5, 5, 5]])
    votes = np.array([[0.5, 0, 0], [0.7, 0, 0], [np.nan] * 3, [np.nan] * 3])
    ids = np.array([0, 0, 0, 1])  # Gaussian 2 joined as hidden; instance 1 has no vote at all
    level = LevelInstances.from_ids("instance", ids, np.array([1, 1, 0, 0], bool), means, votes)
    assert np.allclose(level.vote_centres, [[0.6, 0, 0], [5, 5, 5]])


def test_a_background_gaussian_that_joins_an_instance_becomes_foreground() -> None:
    from votesplat_ns.core.clustering import cluster_levels

    rng = np.random.default_rng(0)
    means = np.concatenate([rng.normal(0, 0.1, (60, 3)), rng.normal(3, 0.1, (60, 3)), [[0.0, 0.0, 0.0]]])
    offsets = np.zeros((len(means), 1, 3))
    support = np.ones((len(means), 1))
    support[-1] = 0  # never voted

    def refine(index, name, ids):
        ids = ids.copy()
        ids[-1] = ids[0]  # joins the first blob, as a hidden Gaussian would
        return ids, {"confidence": np.ones(int(ids.max()) + 1)}

    instances = cluster_levels(means, offsets, support, ("instance",), refine=refine)
    instances.validate()
    level = instances.level("instance")
    assert level.ids[-1] == level.ids[0] and level.foreground[-1]
    assert level.clustering["num_joined_background"] == 1 and level.confidence is not None


def test_gaussians_no_view_sees_move_to_the_instance_whose_hull_holds_them() -> None:
    scene = Scene()
    left = scene.add(box_surface([0, 0, 0], [1, 1, 1]), 0, [1, 1, 2, 2, 3, 3])
    right = scene.add(box_surface([1.1, 0, 0], [2.1, 1, 1]), 1, [4, 4, 5, 5, 6, 6])
    # hidden inside the right box in every view, but put in the left box's instance (by votes mixed at the contact)
    stray = scene.add(box_interior([1.1, 0, 0], [2.1, 1, 1])[::25], 0, [-1] * 6)
    # hidden inside the left box and in its instance: its own hull holds it, it stays
    inner = scene.add(box_interior([0, 0, 0], [1, 1, 1])[::25], 0, [-1] * 6)
    means, labels, table = scene.build()
    out, _, stats = run(means, labels, table)
    assert (out[stray] == out[right[0]]).all() and (out[inner] == out[left[0]]).all()
    assert stats["rehome"]["rehomed"] == len(stray) and stats["num_instances"] == 2
    off, _, stats_off = run(means, labels, table, rehome=False)
    assert (off[stray] == off[left[0]]).all() and "rehome" not in stats_off


def test_a_small_objects_hidden_side_is_not_rehomed_into_its_container() -> None:
    scene = Scene()
    # a bowl-like container (an open box) and a small box resting inside it; the small box's underside no view
    # sees, and it lies outside the hull of the small box's seen top but inside the container's hull
    bowl = scene.add(box_surface([0, 0, 0], [2, 2, 1], bottom=True), 0, [1, 1, 2, 2, 3, 3])
    top = scene.add(box_surface([0.8, 0.8, 0.5], [1.2, 1.2, 0.6]), 1, [4, 4, 5, 5, 6, 6])
    underside = scene.add(box_interior([0.7, 0.7, 0.1], [1.3, 1.3, 0.5]), 1, [-1] * 6)
    means, labels, table = scene.build()
    out, _, stats = run(means, labels, table, hidden=False)
    assert (out[underside] == out[top[0]]).all() and (out[bowl] != out[top[0]]).all()
    assert stats["rehome"]["rehomed"] == 0
    # with the size guard off (join_ratio 0) the underside moves into the bowl, whose hull holds it
    loose, _, _ = run(means, labels, table, hidden=False, join_ratio=0.0)
    assert (loose[underside] == loose[bowl[0]]).all()
