"""Placing templates on the table or ground without overlap, in contact where asked (side by side, on a
flat top, inside a bowl), and turning the placed templates into scene objects."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from votesplat_ns.eval.synthetic.scenes.colours import PALETTE
from votesplat_ns.eval.synthetic.scenes.description import Material, Part, SceneObject
from votesplat_ns.eval.synthetic.scenes.primitives import rot_z, transform_points, translate
from votesplat_ns.eval.synthetic.scenes.templates import (
    _FRUIT_COLOUR,
    FAMILY_KINDS,
    FRUITS,
    TABLETOP_KINDS,
    Template,
    _box,
    _fruit,
)


@dataclass
class _Placed:
    template: Template
    pose: np.ndarray
    colour: str
    on_table: bool = True

    @property
    def xy(self) -> np.ndarray:
        return self.pose[:2, 3]

    @property
    def yaw(self) -> float:
        return math.atan2(self.pose[1, 0], self.pose[0, 0])


def _support(placed: _Placed, direction_yaw: float) -> Optional[float]:
    """Horizontal distance from the object's axis to its side surface along a world direction (None: no contact
    there)."""
    side = placed.template.side
    if side is None:
        return None
    if side.kind in ("cylinder", "sphere"):
        return float(side.radius)
    hx, hy, _ = side.box
    rel = (direction_yaw - placed.yaw) % (math.pi / 2)
    if min(rel, math.pi / 2 - rel) > 1e-6:
        return None  # a box only offers contact along its face normals
    along_x = abs(math.cos(direction_yaw - placed.yaw)) > 0.5
    return hx if along_x else hy


def _contact_height_ok(a: _Placed, b: _Placed) -> bool:
    """A sphere touches a vertical side only if that side reaches up to the sphere's equator."""
    for sph, other in ((a, b), (b, a)):
        ball, side = sph.template.side, other.template.side
        if ball is not None and side is not None and ball.kind == "sphere" and side.kind != "sphere":
            if side.kind == "box":
                side_height = side.box[2]
            else:
                side_height = other.template.height * 0.8
            if side_height < ball.radius + 1e-3:
                return False
    return True


def _touching_pose(rng, anchor: _Placed, template: Template) -> Optional[np.ndarray]:
    side_a, side_b = anchor.template.side, template.side
    if side_a is None or side_b is None:
        return None
    kind_a, kind_b = side_a.kind, side_b.kind
    if kind_a == "box":
        direction = anchor.yaw + rng.integers(4) * (math.pi / 2)
    else:
        direction = rng.uniform(0.0, 2.0 * math.pi)
    if anchor.template.avoid_direction is not None:
        away = anchor.yaw + anchor.template.avoid_direction
        if abs(math.remainder(direction - away, 2.0 * math.pi)) < math.radians(70):
            direction = away + math.pi
    if kind_b == "box":
        yaw_b = direction  # one face of the new box looks back at the anchor
    else:
        yaw_b = rng.uniform(0.0, 2.0 * math.pi)
    if template.avoid_direction is not None:
        yaw_b = direction - template.avoid_direction  # the handle points away from the anchor
    candidate = _Placed(template, np.eye(4), "")
    candidate.pose = rot_z(yaw_b)
    sa = _support(anchor, direction)
    sb = _support(candidate, direction + math.pi)
    if sa is None or sb is None:
        return None
    if kind_a == "sphere" and kind_b == "sphere":
        distance = 2.0 * math.sqrt(side_a.radius * side_b.radius)
    else:
        distance = sa + sb
    xy = anchor.xy + distance * np.array([math.cos(direction), math.sin(direction)])
    pose = translate(xy[0], xy[1], anchor.pose[2, 3]) @ rot_z(yaw_b)
    candidate.pose = pose
    if not _contact_height_ok(anchor, candidate):
        return None
    return pose


def _disc(rng: np.random.Generator, radius: float):
    """``inside`` and ``sample_xy`` of :func:`_place_objects` for a round table of ``radius`` centred at the origin
    (area-uniform samples)."""

    def inside(xy, r):
        return np.linalg.norm(xy) + r <= radius

    def sample_xy(index=0):
        rho = radius * math.sqrt(rng.random())
        phi = rng.uniform(0.0, 2.0 * math.pi)
        return np.array([rho * math.cos(phi), rho * math.sin(phi)])

    return inside, sample_xy


def _place_objects(
    rng: np.random.Generator,
    kinds: Sequence[str],
    sizes: Union[Sequence[float], np.ndarray],
    colours: Sequence[str],
    inside: Callable[[np.ndarray, float], bool],
    sample_xy: Callable[[int], np.ndarray],
    touch_probability: float,
    min_touching: int,
    gap: float = 0.012,
    builders: Dict[str, Callable] = TABLETOP_KINDS,
    existing: Sequence[_Placed] = (),
) -> Tuple[List[_Placed], List[Tuple[int, int]]]:
    """Place objects on the table without overlap; some are put in contact with an earlier object.

    ``existing`` objects are already placed (the new ones avoid them and may touch them); the result
    lists them first, and the touching pairs index that whole list.
    """
    placed: List[_Placed] = list(existing)
    touching: List[Tuple[int, int]] = []
    for index, (kind, size, colour) in enumerate(zip(kinds, sizes, colours)):
        template = builders[kind](rng, size, PALETTE[colour])
        want_touch = len(placed) > 0 and (rng.random() < touch_probability or len(touching) < min_touching)
        pose = None
        partner = None
        if want_touch:
            for _ in range(40):
                anchor_index = int(rng.integers(len(placed)))
                anchor = placed[anchor_index]
                if not anchor.on_table:
                    continue
                candidate = _touching_pose(rng, anchor, template)
                if candidate is None:
                    continue
                if _free(placed, candidate, template, inside, gap, skip=anchor_index):
                    pose, partner = candidate, anchor_index
                    break
        if pose is None:
            for _ in range(2000):
                xy = sample_xy(index)
                candidate = translate(xy[0], xy[1], 0.0) @ rot_z(rng.uniform(0.0, 2.0 * math.pi))
                if _free(placed, candidate, template, inside, gap):
                    pose = candidate
                    break
        if pose is None:
            raise ValueError(
                f"could not place {len(kinds)} objects without overlap; use fewer objects (placed {len(placed) - len(existing)})"
            )
        placed.append(_Placed(template, pose, colour))
        if partner is not None:
            touching.append((partner, len(placed) - 1))
    return placed, touching


def _free(placed, pose, template, inside, gap, skip: Optional[int] = None) -> bool:
    xy = pose[:2, 3]
    if not inside(xy, template.footprint_radius):
        return False
    for i, other in enumerate(placed):
        if i == skip or not other.on_table:
            continue
        if np.linalg.norm(other.xy - xy) < other.template.footprint_radius + template.footprint_radius + gap:
            return False
    return True


def _rest_balls_on_tops(rng, placed: List[_Placed], touching: List[Tuple[int, int]]) -> List[Tuple[int, int]]:
    """Move some balls onto a flat top (box or can lid): a second, vertical kind of contact."""
    for i, item in enumerate(placed):
        if item.template.kind != "ball" or not item.on_table:
            continue
        bases = [j for j, other in enumerate(placed) if other.template.top is not None and (j, i) not in touching]
        if bases and rng.random() < 0.5:
            j = bases[int(rng.integers(len(bases)))]
            pose = _stack_on(rng, placed[j], item.template)
            clear = pose is not None and all(
                np.linalg.norm(other.xy - pose[:2, 3])
                >= other.template.footprint_radius + item.template.footprint_radius + 0.012
                for k, other in enumerate(placed)
                if k not in (i, j)
            )
            if pose is not None and clear:
                item.pose, item.on_table = pose, False
                touching = [t for t in touching if i not in t] + [(j, i)]
    return touching


def _stack_on(rng, base: _Placed, template: Template) -> Optional[np.ndarray]:
    """Pose resting a ball on the flat top of ``base`` (the two touch at one point)."""
    if base.template.top is None or template.kind != "ball" or template.side is None:
        return None
    hx, hy, top_z = base.template.top
    r = template.side.radius
    if r > 1.3 * min(hx, hy):
        return None
    offset = rng.uniform(-0.3, 0.3, size=2) * (hx, hy)
    local = np.array([offset[0], offset[1], top_z])
    world = transform_points(base.pose, local[None])[0]
    return translate(world[0], world[1], world[2]) @ rot_z(rng.uniform(0.0, 2.0 * math.pi))


def _build_objects(placed: Sequence[_Placed], first_part_id: int = 1) -> Tuple[SceneObject, ...]:
    objects = []
    part_id = first_part_id
    for index, item in enumerate(placed):
        parts = []
        for name, primitives, srgb in item.template.parts:
            world_prims = tuple(replace(p, pose=item.pose @ p.pose) for p in primitives)
            red, green, blue = (int(c) for c in srgb)
            parts.append(Part(part_id, name, world_prims, Material(srgb=(red, green, blue))))
            part_id += 1
        interior = transform_points(item.pose, np.asarray(item.template.interior_point)[None])[0]
        name = item.template.kind if item.template.kind in _SELF_COLOURED else f"{item.colour} {item.template.kind}"
        objects.append(SceneObject(index + 1, name, item.template.kind, item.colour, tuple(parts), interior))
    return tuple(objects)


_SELF_COLOURED = {"orange", "lime", "lemon", "plum"}


def _place_objects_after(rng, existing: List[_Placed], kinds, sizes, colours, inside, sample_xy):
    """Place more objects around already-placed ones (no contacts with the existing set)."""
    placed = list(existing)
    start = len(placed)
    for kind, size, colour in zip(kinds, sizes, colours):
        template = TABLETOP_KINDS[kind](rng, size, PALETTE[colour])
        for _ in range(2000):
            xy = sample_xy(0)
            pose = translate(xy[0], xy[1], 0.0) @ rot_z(rng.uniform(0.0, 2.0 * math.pi))
            if _free(placed, pose, template, inside, 0.012):
                placed.append(_Placed(template, pose, colour))
                break
        else:
            raise ValueError("could not place the extra objects without overlap; use fewer objects")
    return placed[start:], []


def _fill_bowl(
    rng, s, zc, ri, fruit_count: int, used_colours: set, bowl_pose: Optional[np.ndarray] = None
) -> List[_Placed]:
    """Up to ``fruit_count`` fruits resting on a bowl's inner wall (the first at the bottom), no two touching.

    ``zc``/``ri``: the bowl's sphere centre height and inner radius (bowl-local); ``bowl_pose`` moves the
    fruit with the bowl (None: the bowl stands at the origin). Picks and records the fruit colours in ``used_colours``.
    """
    fruit_kinds = [str(k) for k in rng.permutation(list(FRUITS))[:fruit_count]]
    fruits: List[_Placed] = []
    centres: List[Tuple[np.ndarray, float]] = []
    for k, kind in enumerate(fruit_kinds):
        free = [c for c in ("red", "green") if c not in used_colours] or ["red"]
        colour = _FRUIT_COLOUR.get(kind) or str(rng.choice(free))
        used_colours.add(colour)
        tmpl = _fruit(kind, FRUITS[kind])(rng, s, PALETTE[colour])
        if tmpl.side is None:
            raise ValueError(f"fruit template {kind!r} has no side shape to rest on the bowl's wall with")
        rf = tmpl.side.radius
        for _ in range(500):
            theta = 0.0 if k == 0 else math.radians(rng.uniform(30.0, 62.0))
            phi = rng.uniform(0.0, 2.0 * math.pi)
            d = ri - rf
            centre = np.array(
                [d * math.sin(theta) * math.cos(phi), d * math.sin(theta) * math.sin(phi), zc - d * math.cos(theta)]
            )
            if all(np.linalg.norm(centre - c) >= rf + rc + 0.002 for c, rc in centres):
                break
        else:
            continue
        centres.append((centre, rf))
        pose = translate(centre[0], centre[1], centre[2] - rf) @ rot_z(rng.uniform(0.0, 2.0 * math.pi))
        if bowl_pose is not None:
            pose = translate(*bowl_pose[:3, 3]) @ pose
        fruits.append(_Placed(tmpl, pose, colour, on_table=False))
    return fruits


def _place_on_top(
    rng, placed: List[_Placed], base_index: int, items, touching: List[Tuple[int, int]], margin: float = 0.01
):
    """Stand ``items`` ((kind, size, colour) ...) on the flat top of ``placed[base_index]``, apart from each other.

    Each one placed touches the base; one that finds no room is left out.
    """
    base = placed[base_index]
    if base.template.top is None:
        raise ValueError(f"a {base.template.kind} has no flat top to stand objects on")
    hx, hy, top_z = base.template.top
    on_top: List[Tuple[np.ndarray, float]] = []
    for kind, size, colour in items:
        template = FAMILY_KINDS[kind](rng, size, PALETTE[colour])
        r = template.footprint_radius
        if r + margin > min(hx, hy):
            continue
        for _ in range(200):
            xy = rng.uniform(-1.0, 1.0, size=2) * (hx - r - margin, hy - r - margin)
            if all(np.linalg.norm(xy - other) >= r + ro + 0.012 for other, ro in on_top):
                break
        else:
            continue
        on_top.append((xy, r))
        pose = base.pose @ translate(xy[0], xy[1], top_z) @ rot_z(rng.uniform(0.0, 2.0 * math.pi))
        placed.append(_Placed(template, pose, colour, on_table=False))
        touching.append((base_index, len(placed) - 1))


def _stack_box(rng, placed: List[_Placed], base_index: int, colour: str, touching: List[Tuple[int, int]]) -> bool:
    """Stand a smaller box on the top of box ``placed[base_index]`` (aligned with it, at least 5 mm inside its edges)."""
    base = placed[base_index]
    if base.template.top is None:
        raise ValueError(f"a {base.template.kind} has no flat top to stack a box on")
    hx_b, hy_b, top_z = base.template.top
    # _box's half extents are at most 0.078 s and 0.065 s
    size = 0.85 * min(hx_b / 0.078, hy_b / 0.065)
    template = _box(rng, size, PALETTE[colour])
    if template.top is None:
        raise ValueError("a box template has no flat top")
    hx_t, hy_t, _ = template.top
    room = np.array([hx_b - hx_t - 0.005, hy_b - hy_t - 0.005])
    if (room < 0).any():
        return False
    offset = rng.uniform(-1.0, 1.0, size=2) * room
    turn = math.pi * int(rng.integers(2))
    pose = base.pose @ translate(offset[0], offset[1], top_z) @ rot_z(turn)
    placed.append(_Placed(template, pose, colour, on_table=False))
    touching.append((base_index, len(placed) - 1))
    return True
