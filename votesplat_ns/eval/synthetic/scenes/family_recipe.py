"""The randomised ``family`` recipe: its seed picks the scene's properties (:func:`family_properties`);
:mod:`votesplat_ns.eval.synthetic.family` names its tuning and test seeds."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np

from votesplat_ns.eval.synthetic.scenes.cameras import (
    _camera_clear,
    _forward_cameras,
    _framing,
    _intrinsics,
    _rings_cameras,
    cut_view_share,
    frame_overflow,
    surface_samples,
)
from votesplat_ns.eval.synthetic.scenes.colours import PALETTE
from votesplat_ns.eval.synthetic.scenes.common import (
    _STREAM_CAMERAS,
    _STREAM_OBJECTS,
    _STREAM_TEXTURES,
    _check_counts,
    _forward_background,
    _pick_kinds,
    _plain_colours,
    _room_background,
    _scene,
)
from votesplat_ns.eval.synthetic.scenes.description import Intrinsics, Scene, _object_box
from votesplat_ns.eval.synthetic.scenes.placement import (
    _build_objects,
    _disc,
    _fill_bowl,
    _place_objects,
    _place_on_top,
    _Placed,
    _rest_balls_on_tops,
    _stack_box,
)
from votesplat_ns.eval.synthetic.scenes.primitives import primitive_mesh, rot_z, translate
from votesplat_ns.eval.synthetic.scenes.templates import FAMILY_FLAT_KINDS, FAMILY_KINDS

_STREAM_FAMILY = 6  # the random stream of family_properties

# what each flat kind is called among the property kinds
_FLAT_PROPERTY = {"monitor": "screen", "table": "table top", "board": "board"}
FAMILY_PROPERTY_KINDS = (
    "360",
    "forward",
    "low ring",
    "several rings",
    "cut by frame",
    "stacked",
    "container",
    "screen",
    "table top",
    "board",
    "textured background",
    "plain background",
)
# camera ring elevation bands (degrees above the look-at point): low, middle, high
_RING_BANDS = ((4.0, 12.0), (18.0, 32.0), (38.0, 58.0))
LOW_RING_DEGREES = 15.0
# nominal footprint radius (metres at size 1) of each kind, to size the table before the objects exist
_NOMINAL_RADIUS = {"monitor": 0.27, "table": 0.4, "board": 0.24, "carton": 0.24, "bowl": 0.14}
_SMALL_KINDS = ("mug", "lamp", "box", "ball", "bottle", "can", "snowman")
_ON_TOP_KINDS = ("mug", "box", "ball", "bottle", "can", "snowman")
# the share of views in which the cut object must overflow the image frame
CUT_VIEW_SHARE = 0.8


@dataclass(frozen=True)
class FamilyProperties:
    """What a ``family`` scene holds; drawn from its seed alone (:func:`family_properties`)."""

    capture: str  # "360" (camera rings around the table) or "forward" (forward-facing, objects 1.3-4 m away)
    ring_elevations: Tuple[float, ...]  # degrees, one per camera ring (360 only)
    cut_object: Optional[str]  # kind of the large object cut by the image frame in most views, or None
    stacked: bool  # a box stands on a larger box
    container: bool  # a bowl holding fruit
    flat: Tuple[str, ...]  # large flat objects among "monitor", "table", "board"
    background: str  # "textured" or "plain"

    @property
    def kinds(self) -> Tuple[str, ...]:
        """The property kinds (:data:`FAMILY_PROPERTY_KINDS`) this scene covers."""
        kinds = [self.capture]
        if any(e < LOW_RING_DEGREES for e in self.ring_elevations):
            kinds.append("low ring")
        if len(self.ring_elevations) > 1:
            kinds.append("several rings")
        if self.cut_object is not None:
            kinds.append("cut by frame")
        if self.stacked:
            kinds.append("stacked")
        if self.container:
            kinds.append("container")
        kinds += [_FLAT_PROPERTY[k] for k in self.flat]
        kinds.append(f"{self.background} background")
        return tuple(kinds)


def family_properties(seed: int) -> FamilyProperties:
    """The properties of the ``family`` scene of ``seed`` (every scene also has objects touching side by side)."""
    rng = np.random.default_rng([seed, _STREAM_FAMILY])
    capture = "forward" if rng.random() < 1.0 / 3.0 else "360"
    rings: Tuple[float, ...] = ()
    if capture == "360":
        bands = sorted(int(b) for b in rng.permutation(len(_RING_BANDS))[: int(rng.integers(1, 4))])
        rings = tuple(round(float(rng.uniform(*_RING_BANDS[b])), 1) for b in bands)
    flat = [k for k in FAMILY_FLAT_KINDS if rng.random() < 0.4]
    if len(flat) > 2:
        flat.pop(int(rng.integers(len(flat))))
    cut = None
    if rng.random() < 0.45:
        candidates = [k for k in flat if k in ("monitor", "table")] or ["carton"]
        cut = candidates[int(rng.integers(len(candidates)))]
    stacked = bool(rng.random() < 0.5)
    container = bool(rng.random() < 0.5)
    background = "plain" if rng.random() < 0.4 else "textured"
    return FamilyProperties(capture, rings, cut, stacked, container, tuple(flat), background)


def _family_ground(
    rng, props: FamilyProperties, palette: List[str], small_size: Tuple[float, float], large_size: Tuple[float, float]
):
    """The objects standing on the table/ground, in placing order: (kind, size, colour) for the large ones and the rest."""
    large = [k for k in props.flat if k != props.cut_object]
    bowl_on_table = props.container and "table" in props.flat and rng.random() < 0.5
    # sizes are relative to the capture's small objects (small_size 1.1-1.5 at 360, 2-3 forward-facing)
    rest: List[Tuple[str, float]] = []
    if props.container and not bowl_on_table:
        rest.append(("bowl", 1.3 * small_size[0] / 1.1 * rng.uniform(0.95, 1.1)))
    if props.stacked and props.cut_object != "carton":
        rest.append(("box", rng.uniform(1.45, 1.6) * small_size[1] / 1.5))  # a box big enough to carry another
    for kind in _pick_kinds(rng, max(2, int(rng.integers(5, 8)) - len(large) - len(rest)), list(_SMALL_KINDS)):
        rest.append((kind, rng.uniform(*small_size)))
    large_items = [(k, rng.uniform(*large_size), palette.pop()) for k in large]
    rest_items = [(k, size, palette.pop()) for k, size in rest]
    return large_items, rest_items, bowl_on_table


def _family_dress(rng, placed, touching, props: FamilyProperties, palette: List[str], small_size, bowl_on_table: bool):
    """Stacks, things on the table top or board, balls on flat tops and fruit in the bowl (in this order)."""
    if props.stacked:
        bases = [i for i, item in enumerate(placed) if item.template.kind in ("carton", "box") and item.on_table]
        base = max(bases, key=lambda i: min(placed[i].template.top[:2]))
        if not _stack_box(rng, placed, base, palette.pop(), touching):
            raise ValueError("family: the stack's base box is too small for another box")
    for index in [i for i, item in enumerate(placed) if item.template.kind in ("table", "board")]:
        kind = placed[index].template.kind
        count = int(rng.integers(1, 3)) if kind == "table" else int(rng.random() < 0.6)
        bowl_here = kind == "table" and bowl_on_table
        count = max(0, min(count, len(palette) - bowl_here))  # every object other than fruit has a colour of its own
        items = [("bowl", 0.9 * small_size[0] * rng.uniform(1.05, 1.2), palette.pop())] if bowl_here else []
        items += [
            (k, rng.uniform(0.9, 1.0) * small_size[0], palette.pop())
            for k in _pick_kinds(rng, count, list(_ON_TOP_KINDS))
        ]
        _place_on_top(rng, placed, index, items, touching)
    touching = _rest_balls_on_tops(rng, placed, touching)
    if props.container:
        (bowl_index,) = [i for i, item in enumerate(placed) if item.template.kind == "bowl"]
        bowl = placed[bowl_index]
        zc, ri = bowl.template.cavity
        bowl_scale = bowl.template.footprint_radius / 0.14  # _bowl's outer radius is 0.14 s
        used = {item.colour for item in placed}
        fruits = _fill_bowl(rng, bowl_scale, zc, ri, int(rng.integers(2, 5)), used, bowl_pose=bowl.pose)
        for fruit in fruits:
            placed.append(fruit)
            touching.append((bowl_index, len(placed) - 1))
    return touching


def _retry_layout(build, attempts: int = 8):
    """Run ``build(grow)`` with a layout grown by 12 % per failed attempt (deterministic: same seed, same tries)."""
    for attempt in range(attempts):
        try:
            return build(1.12**attempt)
        except ValueError as error:
            last = error
    raise ValueError(f"family: could not lay the scene out ({last})")


def _family_360(seed: int, props: FamilyProperties, total: int, intrinsics: Intrinsics):
    rng = np.random.default_rng([seed, _STREAM_OBJECTS])
    small_size = (1.1, 1.5)
    boost = 1.0

    def build(grow: float):
        palette = [str(c) for c in rng.permutation(list(PALETTE))]
        existing: List[_Placed] = []
        if props.cut_object is not None:
            # the cut object stands in the middle, larger than life
            template = FAMILY_KINDS[props.cut_object](rng, boost * rng.uniform(1.35, 1.6), PALETTE[palette[-1]])
            existing.append(_Placed(template, rot_z(rng.uniform(0.0, 2.0 * math.pi)), palette.pop()))
        large, rest, bowl_on_table = _family_ground(rng, props, palette, small_size, (1.0, 1.15))
        nominal = [(_NOMINAL_RADIUS.get(k, 0.08) * size) ** 2 for k, size, _ in large + rest]
        nominal += [item.template.footprint_radius**2 for item in existing]
        radius = grow * max(0.3, math.sqrt(sum(nominal) / 0.5))

        inside, sample_xy = _disc(rng, radius)
        kinds, sizes, colours = (list(v) for v in zip(*(large + rest))) if large + rest else ([], [], [])
        placed, touching = _place_objects(
            rng, kinds, sizes, colours, inside, sample_xy, 0.35, 1, builders=FAMILY_KINDS, existing=existing
        )
        touching = _family_dress(rng, placed, touching, props, palette, small_size, bowl_on_table)
        return placed, touching, radius

    cam_seed = [seed, _STREAM_CAMERAS]
    for _ in range(8):
        placed, touching, radius = _retry_layout(build)
        objects = _build_objects(placed)
        parameters: Dict[str, object] = dict(layout_radius=radius)
        if props.cut_object is None:
            # move the cameras in while every view still holds every object whole
            target, distance = _framing(objects, intrinsics)
            points = np.concatenate([surface_samples(obj, 400) for obj in objects])
            cameras, rings = _rings_cameras(
                np.random.default_rng(cam_seed), total, distance, props.ring_elevations, target
            )
            while True:
                closer = 0.96 * distance
                trial, trial_rings = _rings_cameras(
                    np.random.default_rng(cam_seed), total, closer, props.ring_elevations, target
                )
                if not all(frame_overflow(camera, intrinsics, points, margin=0.04)[0] == 1.0 for camera in trial):
                    break
                distance, cameras, rings = closer, trial, trial_rings
            break
        # move the cameras in until the cut object overflows the frame in most views, keeping them clear of
        # every object; if they must stop first, lay the scene out again with a larger cut object
        cut = objects[0]
        lo, hi = _object_box(cut)
        target = np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, 0.45 * hi[2]])
        points = surface_samples(cut)
        boxes = [_object_box(obj) for obj in objects]
        distance = _framing(objects, intrinsics)[1]
        cameras, rings = _rings_cameras(np.random.default_rng(cam_seed), total, distance, props.ring_elevations, target)
        while cut_view_share(cameras, intrinsics, points) < CUT_VIEW_SHARE:
            closer = 0.95 * distance
            trial, trial_rings = _rings_cameras(
                np.random.default_rng(cam_seed), total, closer, props.ring_elevations, target
            )
            if not _camera_clear(trial, boxes, 0.12):
                break
            distance, cameras, rings = closer, trial, trial_rings
        parameters["cut_view_share"] = cut_view_share(cameras, intrinsics, points)
        if parameters["cut_view_share"] >= CUT_VIEW_SHARE:
            break
        boost *= 1.15
    parameters.update(camera_distance=distance, camera_target=np.asarray(target).tolist(), camera_rings=rings)
    wall_radius = max(2.8, 1.3 * distance + 0.5)
    return (
        objects,
        touching,
        cameras,
        parameters,
        dict(ground_half=wall_radius + 0.2, wall_radius=wall_radius, wall_height=2.5),
    )


def _family_forward(seed: int, props: FamilyProperties, total: int, intrinsics: Intrinsics):
    rng = np.random.default_rng([seed, _STREAM_OBJECTS])
    small_size = (2.0, 3.0)
    near, far = 1.3, 4.0
    tan_half = intrinsics.width / (2.0 * intrinsics.fx)
    half_tan = 0.8 * tan_half

    def build(grow: float):
        palette = [str(c) for c in rng.permutation(list(PALETTE))]
        existing: List[_Placed] = []
        if props.cut_object is not None:
            # near the cameras, across the side of the view: the outer part leaves the frame in every view
            template = FAMILY_KINDS[props.cut_object](rng, rng.uniform(1.6, 1.9), PALETTE[palette[-1]])
            half_x = max(
                np.abs(primitive_mesh(p).vertices[:, 0]).max() for _, prims, _ in template.parts for p in prims
            )
            y = rng.uniform(1.3, 1.7)
            side = 1.0 if rng.random() < 0.5 else -1.0
            # the cameras span x in [-0.32, 0.32]: reach 0.12 m past the farthest frame edge
            x = side * (tan_half * y + 0.32 + 0.12 - half_x)
            existing.append(_Placed(template, translate(x, y, 0.0) @ rot_z(rng.uniform(-0.08, 0.08)), palette.pop()))
        large, rest, bowl_on_table = _family_ground(rng, props, palette, small_size, (1.5, 1.8))
        bands = rng.permutation(max(1, len(rest)))
        depth = far * grow

        def inside(xy, r):
            x, y = xy
            return near <= y - r and y + r <= depth and abs(x) + r <= half_tan * (y - 0.3)

        def sample_xy(index):
            if index < len(large):  # the large ones anywhere in depth
                y = rng.uniform(near, depth)
            else:  # the others each in their own depth band, so the scene spans near to far
                y = near + (depth - near) * (bands[index - len(large)] + rng.random()) / len(bands)
            return np.array([rng.uniform(-1.0, 1.0) * half_tan * y, y])

        kinds, sizes, colours = (list(v) for v in zip(*(large + rest)))
        placed, touching = _place_objects(
            rng, kinds, sizes, colours, inside, sample_xy, 0.35, 1, gap=0.03, builders=FAMILY_KINDS, existing=existing
        )
        touching = _family_dress(rng, placed, touching, props, palette, small_size, bowl_on_table)
        return placed, touching, depth

    placed, touching, depth = _retry_layout(build)
    objects = _build_objects(placed)
    cameras = _forward_cameras(np.random.default_rng([seed, _STREAM_CAMERAS]), total)
    parameters: Dict[str, object] = dict(depth_range=[near, depth])
    if props.cut_object is not None:
        parameters["cut_view_share"] = cut_view_share(cameras, intrinsics, surface_samples(objects[0]))
    return objects, touching, cameras, parameters, None


def family(
    seed: int = 0,
    num_views: int = 48,
    num_eval_views: int = 6,
    width: int = 256,
    height: int = 192,
    num_objects: Optional[int] = None,
    fov_x_degrees: Optional[float] = None,
) -> Scene:
    """A randomised scene whose seed picks its properties (:func:`family_properties`): 360 rings (low, several)
    or forward-facing views, a large object cut by the frame, stacked boxes, a bowl of fruit, screens, tables,
    boards, textured or plain background; some objects always touch side by side."""
    _check_counts(num_views, num_eval_views)
    if num_objects is not None:
        raise ValueError("the family recipe draws its objects from the seed; leave out num_objects (--objects)")
    props = family_properties(seed)
    if fov_x_degrees is None:
        fov_x_degrees = 55.0 if props.capture == "360" else 60.0
    intrinsics = _intrinsics(width, height, fov_x_degrees)
    total = num_views + num_eval_views
    build = _family_360 if props.capture == "360" else _family_forward
    objects, touching, cameras, parameters, room = build(seed, props, total, intrinsics)
    rng_tex = np.random.default_rng([seed, _STREAM_TEXTURES])
    plain = _plain_colours(rng_tex) if props.background == "plain" else None
    if room is None:
        backdrop = _forward_background(rng_tex, plain)
    else:
        backdrop = _room_background(rng_tex, room["ground_half"], room["wall_radius"], room["wall_height"], plain)
    large = [o.id for o in objects if o.kind in ("monitor", "table", "board", "carton")]
    parameters.update(
        properties=asdict(props),
        property_kinds=list(props.kinds),
        num_objects=len(objects),
        large_instances=large,
        cut_instance=objects[0].id if props.cut_object is not None else None,
    )
    # each pair in ascending order (a ball rests on a base placed after it); the other recipes keep their pairs as
    # placed, so that their scenes of a seed stay the same
    pairs = [(min(a, b), max(a, b)) for a, b in touching]
    return _scene("family", seed, objects, backdrop, cameras, intrinsics, num_eval_views, pairs, parameters)
