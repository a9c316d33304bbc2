"""Seeded scene recipes with exact geometry, for datasets with exact instance/part ground truth.

Pure numpy: a recipe returns a :class:`Scene` (objects made of parts made of primitives, a textured
background, lights and cameras); ``render.py`` hands it to mitsuba. Every primitive knows its own
triangle mesh and an analytic distance to its ideal surface, so tests can check rendered depth
against the geometry without the renderer.

Conventions
-----------
* World frame: metres, z up, the table/ground is the plane z = 0.
* Cameras: camera-to-world ``c2w`` [4,4] in OpenCV convention (x right, y down, z forward); the
  intrinsics are shared by all views; pixel centres at (x + 0.5, y + 0.5).
* Ids: instance ids 1..K in placement order, part ids globally unique 1..P, 0 = background.
* Randomness: independent streams ``np.random.default_rng([seed, k])`` for objects, cameras,
  textures and lights, so changing the number of views never changes the objects.

Modules (bottom up): ``primitives`` (transforms, meshes), ``description`` (the :class:`Scene` record),
``colours`` (palette, textures), ``templates`` (object kinds), ``placement``, ``cameras``, ``common``
(version, random streams, backgrounds, lights), then the recipes: ``recipes`` (tabletop360, nested,
forward) and ``family_recipe`` (family). Their public names are importable from this package; names
with a leading underscore are shared between these modules only.
"""

from __future__ import annotations

from typing import Callable, Dict

from votesplat_ns.eval.synthetic.scenes.cameras import (
    cut_view_share as cut_view_share,
    frame_overflow as frame_overflow,
    look_at as look_at,
    surface_samples as surface_samples,
)
from votesplat_ns.eval.synthetic.scenes.colours import (
    PALETTE as PALETTE,
    linear_to_srgb_uint8 as linear_to_srgb_uint8,
    make_texture as make_texture,
    srgb_to_linear as srgb_to_linear,
)
from votesplat_ns.eval.synthetic.scenes.common import GENERATOR_VERSION as GENERATOR_VERSION
from votesplat_ns.eval.synthetic.scenes.description import (
    Camera as Camera,
    Intrinsics as Intrinsics,
    Lighting as Lighting,
    Material as Material,
    Part as Part,
    Scene as Scene,
    SceneObject as SceneObject,
)
from votesplat_ns.eval.synthetic.scenes.family_recipe import (
    CUT_VIEW_SHARE as CUT_VIEW_SHARE,
    FAMILY_PROPERTY_KINDS as FAMILY_PROPERTY_KINDS,
    LOW_RING_DEGREES as LOW_RING_DEGREES,
    FamilyProperties as FamilyProperties,
    family as family,
    family_properties as family_properties,
)
from votesplat_ns.eval.synthetic.scenes.primitives import (
    Box as Box,
    Mesh as Mesh,
    Quad as Quad,
    Revolved as Revolved,
    primitive_mesh as primitive_mesh,
    primitive_surface_distance as primitive_surface_distance,
    rigid_inverse as rigid_inverse,
    rot_x as rot_x,
    rot_z as rot_z,
    solid_frustum as solid_frustum,
    sphere as sphere,
    transform_points as transform_points,
    translate as translate,
)
from votesplat_ns.eval.synthetic.scenes.recipes import forward as forward, nested as nested, tabletop360 as tabletop360
from votesplat_ns.eval.synthetic.scenes.templates import (
    FAMILY_FLAT_KINDS as FAMILY_FLAT_KINDS,
    FAMILY_KINDS as FAMILY_KINDS,
    FRUITS as FRUITS,
    SCREEN_SRGB as SCREEN_SRGB,
    TABLETOP_KINDS as TABLETOP_KINDS,
    Template as Template,
)

RECIPES: Dict[str, Callable[..., Scene]] = {
    "tabletop360": tabletop360,
    "nested": nested,
    "forward": forward,
    "family": family,
}


def make_scene(recipe: str, seed: int = 0, **options) -> Scene:
    """Build a recipe's scene; ``options`` are the recipe's keyword arguments (views, size, objects)."""
    if recipe not in RECIPES:
        raise ValueError(f"unknown recipe {recipe!r}; choose one of {', '.join(sorted(RECIPES))}")
    scene = RECIPES[recipe](seed=seed, **options)
    # what make_scene needs to rebuild this exact scene (written to transforms.json)
    scene.parameters["options"] = dict(options)
    return scene
