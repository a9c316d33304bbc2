"""What every recipe shares: the generator version, the random streams, backgrounds, lighting, the
checks of a recipe's arguments and the assembly of its :class:`Scene`."""

from __future__ import annotations

import math
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from votesplat_ns.eval.synthetic.scenes.cameras import _interleaved_eval
from votesplat_ns.eval.synthetic.scenes.colours import make_texture
from votesplat_ns.eval.synthetic.scenes.description import Lighting, Material, Part, Scene
from votesplat_ns.eval.synthetic.scenes.primitives import Quad, Revolved, rot_x, translate

GENERATOR_VERSION = "1"

# the random streams: np.random.default_rng([seed, k]) for each k
_STREAM_OBJECTS = 1
_STREAM_CAMERAS = 2
_STREAM_TEXTURES = 3
_STREAM_LIGHTS = 4


def _background_materials(rng_tex, textures: Dict[str, tuple], plain_colours):
    """Materials and textures of a background's two pieces: flat ``plain_colours`` sRGB, or the named
    ``textures`` (``make_texture``'s size, two base colours, checks and dots), drawn in this order."""
    if plain_colours is not None:
        return tuple(Material(srgb=colour) for colour in plain_colours), {}
    drawn = {name: make_texture(rng_tex, *spec) for name, spec in textures.items()}
    return tuple(Material(texture=name) for name in drawn), drawn


def _room_background(rng_tex, ground_half: float, wall_radius: float, wall_height: float, plain_colours=None):
    """Table plane and a cylindrical wall: textured, or flat ``(table, wall)`` sRGB colours."""
    materials, textures = _background_materials(
        rng_tex,
        {
            "table": ((256, 256), (180, 150, 110), (150, 120, 85), 8, 60),
            "wall": ((256, 512), (120, 135, 150), (95, 110, 125), 6, 90),
        },
        plain_colours,
    )
    ground = Part(0, "table", (Quad((ground_half, ground_half), uv_tiles=(ground_half, ground_half)),), materials[0])
    wall_profile = np.array([[wall_radius, 0.0], [wall_radius, wall_height]])
    wall = Part(0, "wall", (Revolved((wall_profile,), segments=96),), materials[1])
    return (ground, wall), textures


def _forward_background(rng_tex, plain_colours: Optional[Tuple[Tuple[int, int, int], Tuple[int, int, int]]] = None):
    """Ground and back wall of a forward-facing capture: textured, or flat ``(ground, wall)`` sRGB colours."""
    materials, textures = _background_materials(
        rng_tex,
        {
            "ground": ((256, 256), (170, 160, 120), (140, 130, 95), 8, 70),
            "wall": ((256, 512), (150, 120, 120), (120, 95, 100), 6, 120),
        },
        plain_colours,
    )
    ground = Part(0, "ground", (Quad((4.5, 4.0), pose=translate(0.0, 2.5, 0.0), uv_tiles=(9.0, 8.0)),), materials[0])
    wall = Part(
        0,
        "wall",
        (Quad((4.5, 1.8), pose=translate(0.0, 5.5, 1.8) @ rot_x(math.pi / 2), uv_tiles=(3.0, 1.2)),),
        materials[1],
    )
    return (ground, wall), textures


def _plain_colours(rng_tex) -> Tuple[Tuple[int, int, int], Tuple[int, int, int]]:
    """Flat (ground, wall) sRGB colours: a light ground and a wall of another hue."""
    ground_r, ground_g, ground_b = (int(v) for v in rng_tex.uniform(150, 215, size=3))
    wall_r, wall_g, wall_b = (int(v) for v in rng_tex.uniform(110, 200, size=3))
    return (ground_r, ground_g, ground_b), (wall_r, wall_g, wall_b)


def _lighting(rng_light) -> Lighting:
    azimuth = rng_light.uniform(0.0, 2.0 * math.pi)
    elevation = math.radians(rng_light.uniform(50.0, 65.0))
    toward_sun = np.array(
        [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
    )
    x, y, z = (float(v) for v in -toward_sun)
    return Lighting((x, y, z), sun_irradiance=1.9, ambient_radiance=0.38)


def _scene(recipe: str, seed: int, objects, room, cameras, intrinsics, num_eval_views: int, touching, parameters):
    """A recipe's :class:`Scene`: ``room`` is its (background, textures), ``touching`` pairs of indices into
    ``objects`` (instance ids are one more); held-out views interleave with the others, the lights come from the seed."""
    background, textures = room
    return Scene(
        recipe=recipe,
        seed=seed,
        objects=objects,
        background=background,
        textures=textures,
        cameras=tuple(cameras),
        eval_indices=_interleaved_eval(len(cameras), num_eval_views),
        intrinsics=intrinsics,
        lighting=_lighting(np.random.default_rng([seed, _STREAM_LIGHTS])),
        touching=tuple(sorted((a + 1, b + 1) for a, b in touching)),
        parameters=parameters,
    )


def _check_counts(num_views: int, num_eval_views: int):
    if num_views < 1:
        raise ValueError(f"num_views must be at least 1 (got {num_views})")
    if num_eval_views < 0:
        raise ValueError(f"num_eval_views must be 0 or more (got {num_eval_views})")


def _pick_kinds(rng, count: int, allowed: Sequence[str]) -> List[str]:
    kinds = list(rng.permutation(allowed))
    while len(kinds) < count:
        kinds.append(allowed[int(rng.integers(len(allowed)))])
    return kinds[:count]
