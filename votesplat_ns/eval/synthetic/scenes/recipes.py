"""The fixed recipes: ``tabletop360`` (objects on a table, cameras all around), ``nested`` (a bowl of
fruit) and ``forward`` (a forward-facing capture)."""

from __future__ import annotations

import math
from typing import List, Optional, Tuple

import numpy as np

from votesplat_ns.eval.synthetic.scenes.cameras import _forward_cameras, _framing, _intrinsics, _ring_cameras
from votesplat_ns.eval.synthetic.scenes.colours import PALETTE
from votesplat_ns.eval.synthetic.scenes.common import (
    _STREAM_CAMERAS,
    _STREAM_OBJECTS,
    _STREAM_TEXTURES,
    _check_counts,
    _forward_background,
    _pick_kinds,
    _room_background,
    _scene,
)
from votesplat_ns.eval.synthetic.scenes.description import Scene
from votesplat_ns.eval.synthetic.scenes.placement import (
    _build_objects,
    _disc,
    _fill_bowl,
    _place_objects,
    _place_objects_after,
    _Placed,
    _rest_balls_on_tops,
)
from votesplat_ns.eval.synthetic.scenes.primitives import rot_z, translate
from votesplat_ns.eval.synthetic.scenes.templates import TABLETOP_KINDS, _bowl


def _pick_objects(rng, num_objects: Optional[int], default_range: Tuple[int, int]) -> Tuple[int, List[str], List[str]]:
    """How many tabletop objects (``num_objects``, or drawn from ``default_range``), their kinds and distinct colours."""
    count = int(rng.integers(*default_range)) if num_objects is None else int(num_objects)
    if not 1 <= count <= len(PALETTE):
        raise ValueError(f"num_objects must be between 1 and {len(PALETTE)} (got {count})")
    kinds = _pick_kinds(rng, count, list(TABLETOP_KINDS))
    colours = [str(c) for c in rng.permutation(list(PALETTE))[:count]]
    return count, kinds, colours


def _room(seed: int):
    """The textured room of the table recipes (tabletop360, nested)."""
    return _room_background(np.random.default_rng([seed, _STREAM_TEXTURES]), 3.0, 2.8, 1.8)


def _table_views(seed: int, objects, total: int, intrinsics, elevation_range: Tuple[float, float]):
    """``total`` ring cameras over ``elevation_range`` (degrees) that frame every object: (cameras, target, distance)."""
    target, distance = _framing(objects, intrinsics)
    cameras = _ring_cameras(np.random.default_rng([seed, _STREAM_CAMERAS]), total, distance, elevation_range, target)
    return cameras, target, distance


def tabletop360(
    seed: int = 0,
    num_views: int = 48,
    num_eval_views: int = 6,
    width: int = 256,
    height: int = 192,
    num_objects: Optional[int] = None,
    fov_x_degrees: float = 55.0,
) -> Scene:
    """6-12 objects (or ``num_objects``) on a textured table, some touching; cameras all around them."""
    _check_counts(num_views, num_eval_views)
    rng = np.random.default_rng([seed, _STREAM_OBJECTS])
    count, kinds, colours = _pick_objects(rng, num_objects, (6, 13))
    sizes = rng.uniform(1.1, 1.6, size=count)
    table_radius = 0.32 + 0.025 * count
    inside, sample_xy = _disc(rng, table_radius)
    placed, touching = _place_objects(rng, kinds, sizes, colours, inside, sample_xy, 0.35, min(1, count - 1))
    touching = _rest_balls_on_tops(rng, placed, touching)
    objects = _build_objects(placed)
    intrinsics = _intrinsics(width, height, fov_x_degrees)
    cameras, target, distance = _table_views(seed, objects, num_views + num_eval_views, intrinsics, (22.0, 50.0))
    parameters = dict(
        num_objects=count, table_radius=table_radius, camera_distance=distance, camera_target=target.tolist()
    )
    return _scene("tabletop360", seed, objects, _room(seed), cameras, intrinsics, num_eval_views, touching, parameters)


def nested(
    seed: int = 0,
    num_views: int = 48,
    num_eval_views: int = 6,
    width: int = 256,
    height: int = 192,
    num_objects: Optional[int] = None,
    fov_x_degrees: float = 55.0,
) -> Scene:
    """A bowl holding 2-4 fruits (containment: each fruit touches the bowl's inside) plus 2-3 other objects."""
    _check_counts(num_views, num_eval_views)
    rng = np.random.default_rng([seed, _STREAM_OBJECTS])
    s = rng.uniform(1.3, 1.5)
    bowl_colour = str(rng.choice(["blue", "white", "teal", "grey"]))
    template, (zc, ri) = _bowl(rng, s, PALETTE[bowl_colour])
    bowl = _Placed(template, translate(0.0, 0.0, 0.0) @ rot_z(rng.uniform(0, 2 * math.pi)), bowl_colour)
    fruit_count = int(rng.integers(2, 5))
    used_colours = {bowl_colour}
    fruits = _fill_bowl(rng, s, zc, ri, fruit_count, used_colours)
    extra = int(rng.integers(2, 4)) if num_objects is None else max(0, int(num_objects) - 1 - len(fruits))
    others = [k for k in TABLETOP_KINDS if k not in ("lamp",)]
    kinds = _pick_kinds(rng, extra, others)
    colours = [str(c) for c in rng.permutation([c for c in PALETTE if c not in used_colours])[:extra]]
    table_radius = 0.5
    inside, sample_xy = _disc(rng, table_radius)
    placed = [bowl] + fruits
    rest, rest_touching = _place_objects_after(
        rng, placed, kinds, rng.uniform(1.1, 1.4, size=extra), colours, inside, sample_xy
    )
    all_placed = placed + rest
    touching = [(0, 1 + i) for i in range(len(fruits))] + rest_touching
    objects = _build_objects(all_placed)
    intrinsics = _intrinsics(width, height, fov_x_degrees)
    cameras, _, _ = _table_views(seed, objects, num_views + num_eval_views, intrinsics, (32.0, 62.0))
    parameters = dict(num_objects=len(objects), bowl_instance=1, fruit_instances=[2 + i for i in range(len(fruits))])
    return _scene("nested", seed, objects, _room(seed), cameras, intrinsics, num_eval_views, touching, parameters)


def forward(
    seed: int = 0,
    num_views: int = 24,
    num_eval_views: int = 4,
    width: int = 256,
    height: int = 192,
    num_objects: Optional[int] = None,
    fov_x_degrees: float = 60.0,
) -> Scene:
    """Forward-facing capture: cameras on a small vertical plane all looking +y, objects 1.2-4 m away."""
    _check_counts(num_views, num_eval_views)
    rng = np.random.default_rng([seed, _STREAM_OBJECTS])
    count, kinds, colours = _pick_objects(rng, num_objects, (6, 10))
    sizes = rng.uniform(2.0, 3.2, size=count)
    near, far = 1.3, 4.0
    half_tan = 0.8 * math.tan(math.radians(fov_x_degrees) / 2.0)

    def inside(xy, r):
        x, y = xy
        return near <= y - r and y + r <= far and abs(x) + r <= half_tan * (y - 0.3)

    # each object gets its own depth band (in shuffled order) so the scene spans near to far
    bands = rng.permutation(count)

    def sample_xy(index):
        y = near + (far - near) * (bands[index] + rng.random()) / count
        return np.array([rng.uniform(-1.0, 1.0) * half_tan * y, y])

    placed, touching = _place_objects(rng, kinds, sizes, colours, inside, sample_xy, 0.2, min(1, count - 1), gap=0.03)
    objects = _build_objects(placed)
    room = _forward_background(np.random.default_rng([seed, _STREAM_TEXTURES]))
    cameras = _forward_cameras(np.random.default_rng([seed, _STREAM_CAMERAS]), num_views + num_eval_views)
    intrinsics = _intrinsics(width, height, fov_x_degrees)
    parameters = dict(num_objects=count, depth_range=[near, far])
    return _scene("forward", seed, objects, room, cameras, intrinsics, num_eval_views, touching, parameters)
