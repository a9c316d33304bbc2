"""Object templates: every kind of object a recipe can place, built in its object-local frame (origin at
the bottom centre, z up) from primitives."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable, Dict, Literal, Optional, Tuple

import numpy as np

from votesplat_ns.eval.synthetic.scenes.colours import PALETTE, _shade
from votesplat_ns.eval.synthetic.scenes.primitives import (
    Box,
    Primitive,
    Revolved,
    _arc,
    rot_x,
    solid_frustum,
    sphere,
    translate,
)


@dataclass(frozen=True)
class Side:
    """A template's lateral contact shape: a vertical cylinder or a sphere of ``radius``, or a box of half extents
    and height ``box`` (hx, hy, height)."""

    kind: Literal["cylinder", "sphere", "box"]
    radius: float = 0.0
    box: Tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Template:
    kind: str
    parts: Tuple[Tuple[str, Tuple[Primitive, ...], Tuple[int, int, int]], ...]  # (name, primitives, srgb)
    footprint_radius: float  # bounding circle on the table, about the local origin
    side: Optional[Side]  # lateral contact shape (None: no side contact)
    avoid_direction: Optional[float]  # local yaw that a touching neighbour must not come from (mug handle)
    top: Optional[Tuple[float, float, float]]  # flat top for stacking: (half x, half y, height)
    interior_point: Tuple[float, float, float]
    height: float
    cavity: Optional[Tuple[float, float]] = None  # container: (height of the bowl's sphere centre, inner radius)


def _mug(rng, s, colour):
    r = 0.05 * s * rng.uniform(0.9, 1.1)
    h = 0.11 * s * rng.uniform(0.9, 1.1)
    t = 0.1 * r
    body = Revolved(
        (
            np.array([[0.0, 0.0], [r, 0.0]]),
            np.array([[r, 0.0], [r, h]]),
            np.array([[r, h], [r - t, h]]),
            np.array([[r - t, h], [r - t, t]]),
            np.array([[r - t, t], [0.0, t]]),
        )
    )
    tube = 0.12 * h
    ring = 0.3 * h
    circle = _arc((ring, 0.0), tube, 0.0, 2.0 * math.pi, 17)
    handle = Revolved(
        (circle,),
        pose=translate(r - 0.5 * t, 0.0, 0.5 * h) @ rot_x(math.pi / 2),
        angle_range=(-math.pi / 2, math.pi / 2),
        cap_ends=True,
        segments=24,
    )
    return Template(
        kind="mug",
        parts=(("body", (body,), colour), ("handle", (handle,), _shade(colour, 0.6))),
        footprint_radius=r + ring + tube - 0.5 * t,
        side=Side("cylinder", radius=r),
        avoid_direction=0.0,
        top=None,
        interior_point=(0.0, 0.0, 0.5 * t),
        height=h,
    )


def _lamp(rng, s, colour):
    rb, hb = 0.065 * s, 0.02 * s
    rp, hp = 0.011 * s, 0.22 * s * rng.uniform(0.9, 1.15)
    rs0, rs1, hs = 0.085 * s, 0.045 * s, 0.08 * s
    base = Revolved(
        (
            np.array([[0.0, 0.0], [rb, 0.0]]),
            np.array([[rb, 0.0], [0.8 * rb, hb]]),
            np.array([[0.8 * rb, hb], [0.0, hb]]),
        )
    )
    pole = solid_frustum(rp, rp, hp, translate(0.0, 0.0, hb - 0.002 * s), segments=16)
    shade_z = hb + hp - 0.5 * hs
    shade = solid_frustum(rs0, rs1, hs, translate(0.0, 0.0, shade_z))
    return Template(
        kind="lamp",
        parts=(
            ("base", (base,), _shade(colour, 0.5)),
            ("pole", (pole,), PALETTE["grey"]),
            ("shade", (shade,), colour),
        ),
        footprint_radius=max(rb, rs0),
        side=None,
        avoid_direction=None,
        top=None,
        interior_point=(0.0, 0.0, shade_z + 0.5 * hs),
        height=shade_z + hs,
    )


def _box(rng, s, colour):
    hx, hy = 0.06 * s * rng.uniform(0.8, 1.3), 0.05 * s * rng.uniform(0.8, 1.3)
    hz = 0.045 * s * rng.uniform(0.8, 1.4)
    return _box_shape("box", hx, hy, hz, 0.012 * s, colour)


def _box_shape(kind: str, hx: float, hy: float, hz: float, ht: float, colour) -> Template:
    """A box body (half extents hx, hy, hz) under a lid of half height ``ht``."""
    # the lid is flush with the body so a neighbour touching the box touches both over their full height
    e = 0.0
    body = Box((hx, hy, hz), pose=translate(0.0, 0.0, hz))
    lid = Box((hx + e, hy + e, ht), pose=translate(0.0, 0.0, 2 * hz + ht))
    return Template(
        kind=kind,
        parts=(("body", (body,), colour), ("lid", (lid,), _shade(colour, 1.45))),
        footprint_radius=math.hypot(hx + e, hy + e),
        side=Side("box", box=(hx + e, hy + e, 2 * hz + 2 * ht)),
        avoid_direction=None,
        top=(hx + e, hy + e, 2 * hz + 2 * ht),
        interior_point=(0.0, 0.0, hz),
        height=2 * hz + 2 * ht,
    )


def _ball(rng, s, colour):
    r = 0.055 * s * rng.uniform(0.85, 1.2)
    return Template(
        kind="ball",
        parts=(("ball", (sphere(r, translate(0.0, 0.0, r)),), colour),),
        footprint_radius=r,
        side=Side("sphere", radius=r),
        avoid_direction=None,
        top=None,
        interior_point=(0.0, 0.0, r),
        height=2 * r,
    )


def _bottle(rng, s, colour):
    r, h = 0.038 * s, 0.14 * s * rng.uniform(0.9, 1.15)
    rn, hs, hn = 0.014 * s, 0.045 * s, 0.035 * s
    body = solid_frustum(r, r, h, np.eye(4))
    neck = Revolved(
        (
            np.array([[0.0, h], [r, h]]),
            np.array([[r, h], [rn, h + hs]]),
            np.array([[rn, h + hs], [rn, h + hs + hn]]),
            np.array([[rn, h + hs + hn], [0.0, h + hs + hn]]),
        )
    )
    rc, hc = 1.3 * rn, 0.025 * s
    cap = solid_frustum(rc, rc, hc, translate(0.0, 0.0, h + hs + hn - 0.4 * hc), segments=24)
    return Template(
        kind="bottle",
        parts=(("body", (body,), colour), ("neck", (neck,), _shade(colour, 1.4)), ("cap", (cap,), PALETTE["black"])),
        footprint_radius=r,
        side=Side("cylinder", radius=r),
        avoid_direction=None,
        top=None,
        interior_point=(0.0, 0.0, 0.5 * h),
        height=h + hs + hn + 0.6 * hc,
    )


def _can(rng, s, colour):
    r, h = 0.045 * s * rng.uniform(0.9, 1.15), 0.1 * s * rng.uniform(0.85, 1.2)
    rl, hl = r, 0.018 * s  # flush lid: side contacts hold over the full height
    body = solid_frustum(r, r, h, np.eye(4))
    lid = solid_frustum(rl, rl, hl, translate(0.0, 0.0, h))
    return Template(
        kind="can",
        parts=(("body", (body,), colour), ("lid", (lid,), _shade(colour, 0.55))),
        footprint_radius=rl,
        side=Side("cylinder", radius=rl),
        avoid_direction=None,
        top=(0.7 * rl, 0.7 * rl, h + hl),
        interior_point=(0.0, 0.0, 0.5 * h),
        height=h + hl,
    )


def _snowman(rng, s, colour):
    r1, r2 = 0.06 * s, 0.04 * s * rng.uniform(0.9, 1.1)
    z2 = 2 * r1 + 0.8 * r2
    rh, hh = 0.7 * r2, 0.04 * s
    hat_z = z2 + 0.75 * r2
    return Template(
        kind="snowman",
        parts=(
            ("body", (sphere(r1, translate(0.0, 0.0, r1)),), colour),
            ("head", (sphere(r2, translate(0.0, 0.0, z2)),), _shade(colour, 1.35)),
            ("hat", (solid_frustum(rh, rh, hh, translate(0.0, 0.0, hat_z), segments=24),), PALETTE["black"]),
        ),
        footprint_radius=r1,
        side=Side("sphere", radius=r1),
        avoid_direction=None,
        top=None,
        interior_point=(0.0, 0.0, r1),
        height=hat_z + hh,
    )


TABLETOP_KINDS: Dict[str, Callable] = {
    "mug": _mug,
    "lamp": _lamp,
    "box": _box,
    "ball": _ball,
    "bottle": _bottle,
    "can": _can,
    "snowman": _snowman,
}


# --------------------------------------------------------------------------------------------
# a bowl and fruit (the nested recipe, and the family's container)


def _fruit(kind: str, radius: float):
    def build(rng, s, colour):
        r = radius * s * rng.uniform(0.9, 1.1)
        parts = [("body", (sphere(r, translate(0.0, 0.0, r)),), colour)]
        height = 2 * r
        if kind == "apple":
            stem = solid_frustum(0.1 * r, 0.07 * r, 0.45 * r, translate(0.0, 0.0, 1.85 * r), segments=12)
            parts.append(("stem", (stem,), PALETTE["brown"]))
            height = 2.3 * r
        return Template(kind, tuple(parts), r, Side("sphere", radius=r), None, None, (0.0, 0.0, r), height)

    return build


def _bowl(rng, s, colour):
    ro = 0.14 * s
    ri = ro - 0.012 * s
    rf, hf = 0.45 * ro, 0.025 * s
    zc = hf - 0.004 * s + ro
    n = 20
    outer = _arc((0.0, 0.0), ro, -math.pi / 2, 0.0, n)
    inner = _arc((0.0, 0.0), ri, 0.0, -math.pi / 2, n)
    outer[0, 0] = inner[-1, 0] = 0.0
    body = Revolved((outer, np.array([[ro, 0.0], [ri, 0.0]]), inner), pose=translate(0.0, 0.0, zc), segments=64)
    foot = Revolved(
        (
            np.array([[0.0, 0.0], [rf, 0.0]]),
            np.array([[rf, 0.0], [0.8 * rf, hf]]),
            np.array([[0.8 * rf, hf], [0.0, hf]]),
        )
    )
    return Template(
        kind="bowl",
        parts=(("body", (body,), colour), ("foot", (foot,), _shade(colour, 0.6))),
        footprint_radius=ro,
        side=None,
        avoid_direction=None,
        top=None,
        interior_point=(0.0, 0.0, zc - 0.5 * (ro + ri)),
        height=zc,
    ), (zc, ri)


FRUITS = {"apple": 0.042, "orange": 0.045, "lime": 0.033, "plum": 0.032, "lemon": 0.038}
_FRUIT_COLOUR = {"orange": "orange", "lime": "green", "plum": "purple", "lemon": "yellow"}


# --------------------------------------------------------------------------------------------
# the family recipe's large objects


SCREEN_SRGB = (28, 32, 40)


def _monitor(rng, s, colour):
    """A flat screen on a stand (screen, housing, stand); the screen faces local -y."""
    hw = rng.uniform(0.21, 0.3) * s  # half width
    hh = hw * rng.uniform(0.55, 0.65)  # half height
    ht = 0.015 * s  # half thickness of the housing
    foot_hx, foot_hy, foot_hz = 0.09 * s, 0.07 * s, 0.006 * s
    zc = 2 * foot_hz + rng.uniform(0.06, 0.1) * s + hh  # housing centre
    housing = Box((hw, ht, hh), pose=translate(0.0, 0.0, zc))
    pane = 0.0015 * s
    bezel = 0.012 * s
    screen = Box((hw - bezel, pane, hh - bezel), pose=translate(0.0, -(ht + pane), zc))
    foot = Box((foot_hx, foot_hy, foot_hz), pose=translate(0.0, 0.0, foot_hz))
    neck_hy = 0.01 * s
    neck_hz = 0.5 * (zc - 2 * foot_hz)
    neck = Box((0.025 * s, neck_hy, neck_hz), pose=translate(0.0, ht + neck_hy, 2 * foot_hz + neck_hz))
    return Template(
        kind="monitor",
        parts=(
            ("screen", (screen,), SCREEN_SRGB),
            ("housing", (housing,), colour),
            ("stand", (neck, foot), _shade(colour, 0.6)),
        ),
        footprint_radius=math.hypot(hw, foot_hy),
        side=None,
        avoid_direction=None,
        top=None,
        interior_point=(0.0, 0.0, zc),
        height=zc + hh,
    )


def _table(rng, s, colour):
    """A low table: a top on four legs; things can stand on its top."""
    hx, hy = rng.uniform(0.28, 0.36) * s, rng.uniform(0.18, 0.24) * s
    height = rng.uniform(0.22, 0.3) * s
    tt, leg = 0.012 * s, 0.018 * s  # half thickness of the top, half width of a leg
    top = Box((hx, hy, tt), pose=translate(0.0, 0.0, height - tt))
    leg_hz = 0.5 * (height - 2 * tt)
    inset = 0.03 * s + leg
    legs = tuple(
        Box((leg, leg, leg_hz), pose=translate(sx * (hx - inset), sy * (hy - inset), leg_hz))
        for sx in (-1.0, 1.0)
        for sy in (-1.0, 1.0)
    )
    return Template(
        kind="table",
        parts=(("top", (top,), colour), ("legs", legs, _shade(colour, 0.55))),
        footprint_radius=math.hypot(hx, hy),
        side=None,
        avoid_direction=None,
        top=(hx, hy, height),
        interior_point=(0.0, 0.0, height - tt),
        height=height,
    )


def _board(rng, s, colour):
    """A thin board lying flat (a tray or cutting board); things can lie on it."""
    hx, hy = rng.uniform(0.16, 0.24) * s, rng.uniform(0.1, 0.15) * s
    hz = rng.uniform(0.006, 0.01) * s
    body = Box((hx, hy, hz), pose=translate(0.0, 0.0, hz))
    return Template(
        kind="board",
        parts=(("board", (body,), colour),),
        footprint_radius=math.hypot(hx, hy),
        side=Side("box", box=(hx, hy, 2 * hz)),
        avoid_direction=None,
        top=(hx, hy, 2 * hz),
        interior_point=(0.0, 0.0, hz),
        height=2 * hz,
    )


def _carton(rng, s, colour):
    """A large lidded box (body, lid)."""
    hx, hy = rng.uniform(0.14, 0.2) * s, rng.uniform(0.12, 0.18) * s
    return _box_shape("carton", hx, hy, rng.uniform(0.16, 0.26) * s, 0.015 * s, colour)


def _bowl_template(rng, s, colour):
    template, cavity = _bowl(rng, s, colour)
    return replace(template, cavity=cavity)


FAMILY_KINDS: Dict[str, Callable] = {
    **TABLETOP_KINDS,
    "monitor": _monitor,
    "table": _table,
    "board": _board,
    "carton": _carton,
    "bowl": _bowl_template,
}
FAMILY_FLAT_KINDS = ("monitor", "table", "board")
