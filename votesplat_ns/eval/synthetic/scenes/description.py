"""What a recipe returns: a :class:`Scene` of objects made of parts made of primitives, a background,
cameras, intrinsics and lights."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import numpy as np

from votesplat_ns.eval.synthetic.scenes.primitives import (
    Primitive,
    primitive_mesh,
    primitive_solid_distance,
    primitive_surface_distance,
    rigid_inverse,
)


def _object_box(obj) -> Tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (min, max) of a scene object's meshes."""
    verts = np.concatenate([primitive_mesh(p).vertices for part in obj.parts for p in part.primitives])
    return verts.min(axis=0), verts.max(axis=0)


@dataclass(frozen=True)
class Material:
    """Diffuse albedo: a flat sRGB colour, or a named texture of the scene (linear values)."""

    srgb: Tuple[int, int, int] = (128, 128, 128)
    texture: Optional[str] = None


@dataclass(frozen=True)
class Part:
    id: int  # 0 for background pieces
    name: str
    primitives: Tuple[Primitive, ...]
    material: Material


@dataclass(frozen=True)
class SceneObject:
    id: int
    name: str
    kind: str
    colour: str
    parts: Tuple[Part, ...]
    interior_point: np.ndarray  # a point strictly inside the object's material


@dataclass(frozen=True)
class Camera:
    c2w: np.ndarray  # [4,4] camera-to-world, OpenCV convention

    @property
    def viewmat(self) -> np.ndarray:
        """World-to-camera [4,4] (OpenCV), as gsplat uses."""
        return rigid_inverse(self.c2w)


@dataclass(frozen=True)
class Intrinsics:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def fov_x_degrees(self) -> float:
        return math.degrees(2.0 * math.atan(self.width / (2.0 * self.fx)))


@dataclass(frozen=True)
class Lighting:
    sun_direction: Tuple[float, float, float]  # direction the light travels (pointing down)
    sun_irradiance: float
    ambient_radiance: float


@dataclass(frozen=True)
class Scene:
    recipe: str
    seed: int
    objects: Tuple[SceneObject, ...]
    background: Tuple[Part, ...]
    textures: Dict[str, np.ndarray]  # name -> [H,W,3] float32 linear albedo
    cameras: Tuple[Camera, ...]
    eval_indices: Tuple[int, ...]
    intrinsics: Intrinsics
    lighting: Lighting
    touching: Tuple[Tuple[int, int], ...]  # instance-id pairs whose surfaces touch
    parameters: Dict[str, object]

    @property
    def parts(self) -> List[Tuple[int, Part]]:
        """(instance id, part) for every object part, background pieces excluded."""
        return [(obj.id, part) for obj in self.objects for part in obj.parts]

    def object_by_id(self, instance_id: int) -> SceneObject:
        for obj in self.objects:
            if obj.id == instance_id:
                return obj
        raise KeyError(f"no object with instance id {instance_id}")

    def object_bounds(self, obj: SceneObject) -> Tuple[np.ndarray, np.ndarray]:
        return _object_box(obj)

    def part_surface_distance(self, part: Part, points_world: np.ndarray) -> np.ndarray:
        return np.min([primitive_surface_distance(p, points_world) for p in part.primitives], axis=0)

    def part_solid_distance(self, part: Part, points_world: np.ndarray) -> np.ndarray:
        """0 inside a closed primitive of the part, else the distance to its surface."""
        return np.min([primitive_solid_distance(p, points_world) for p in part.primitives], axis=0)

    def object_surface_distance(self, obj: SceneObject, points_world: np.ndarray) -> np.ndarray:
        return np.min([self.part_surface_distance(part, points_world) for part in obj.parts], axis=0)
