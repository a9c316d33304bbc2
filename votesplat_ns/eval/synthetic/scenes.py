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
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

GENERATOR_VERSION = "1"

_STREAM_OBJECTS = 1
_STREAM_CAMERAS = 2
_STREAM_TEXTURES = 3
_STREAM_LIGHTS = 4


# --------------------------------------------------------------------------------------------
# rigid transforms


def rot_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    m = np.eye(4)
    m[1:3, 1:3] = [[c, -s], [s, c]]
    return m


def rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    m = np.eye(4)
    m[0:2, 0:2] = [[c, -s], [s, c]]
    return m


def translate(x: float, y: float, z: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def transform_points(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def rigid_inverse(matrix: np.ndarray) -> np.ndarray:
    inv = np.eye(4)
    inv[:3, :3] = matrix[:3, :3].T
    inv[:3, 3] = -matrix[:3, :3].T @ matrix[:3, 3]
    return inv


# --------------------------------------------------------------------------------------------
# primitives


def _segment_distance_2d(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    denom = float(ab @ ab)
    t = np.zeros(len(points)) if denom == 0.0 else np.clip(((points - a) @ ab) / denom, 0.0, 1.0)
    closest = a + t[:, None] * ab
    return np.linalg.norm(points - closest, axis=1)


def _polyline_distance_2d(points: np.ndarray, pieces: Sequence[np.ndarray]) -> np.ndarray:
    best = np.full(len(points), np.inf)
    for piece in pieces:
        for a, b in zip(piece[:-1], piece[1:]):
            best = np.minimum(best, _segment_distance_2d(points, a, b))
    return best


def _inside_polygon_2d(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    inside = np.zeros(len(points), dtype=bool)
    x, y = points[:, 0], points[:, 1]
    n = len(polygon)
    for i in range(n):
        (x0, y0), (x1, y1) = polygon[i], polygon[(i + 1) % n]
        crosses = (y0 > y) != (y1 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_at = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
        inside ^= crosses & (x < x_at)
    return inside


@dataclass(frozen=True)
class Mesh:
    vertices: np.ndarray  # [V,3] float64
    faces: np.ndarray  # [F,3] int64
    uvs: np.ndarray  # [V,2] float64
    normals: np.ndarray  # [V,3] unit, oriented with the face winding


def _smooth_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, shared by vertices at the same position (closes UV seams and poles).

    Callers pass one smooth piece at a time so that sharp profile corners stay sharp.
    """
    tri = vertices[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    quantised = np.ascontiguousarray(np.round(vertices * 1e9).astype(np.int64))
    _, group = np.unique(quantised.view(np.dtype((np.void, 24))).ravel(), return_inverse=True)
    group = group.reshape(-1)
    acc = np.zeros((group.max() + 1, 3))
    for k in range(3):
        np.add.at(acc, group[faces[:, k]], face_n)
    normals = acc[group]
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    unused = length[:, 0] < 1e-20
    normals = np.where(unused[:, None], np.array([0.0, 0.0, 1.0]), normals / np.maximum(length, 1e-30))
    return normals


@dataclass(frozen=True)
class Revolved:
    """A surface of revolution about the local z axis.

    ``pieces`` are polylines in the (rho, z) half plane; they are revolved separately so that the
    renderer's smooth normals never round off a sharp profile corner. ``angle_range`` restricts the
    sweep (radians, counter-clockwise from +x); a partial sweep of a closed profile gets flat end caps
    when ``cap_ends``.
    """

    pieces: Tuple[np.ndarray, ...]
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    angle_range: Optional[Tuple[float, float]] = None
    cap_ends: bool = False
    segments: int = 48

    def local_mesh(self) -> Mesh:
        a0, a1 = self.angle_range if self.angle_range is not None else (0.0, 2.0 * math.pi)
        angles = np.linspace(a0, a1, self.segments + 1)
        vertices, faces, uvs, normals = [], [], [], []
        offset = 0
        for piece in self.pieces:
            piece = np.asarray(piece, dtype=np.float64)
            m = len(piece)
            rho, z = piece[:, 0], piece[:, 1]
            lengths = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(piece, axis=0), axis=1))])
            v_coord = lengths / max(lengths[-1], 1e-12)
            ca, sa = np.cos(angles), np.sin(angles)
            verts = np.stack(
                [rho[:, None] * ca[None, :], rho[:, None] * sa[None, :], np.broadcast_to(z[:, None], (m, len(angles)))],
                axis=-1,
            ).reshape(-1, 3)
            uv = np.stack(
                np.broadcast_arrays(np.linspace(0.0, 1.0, len(angles))[None, :], v_coord[:, None]), axis=-1
            ).reshape(-1, 2)
            idx = np.arange(m * len(angles)).reshape(m, len(angles)) + offset
            quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], axis=-1).reshape(-1, 4)
            tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
            tris = _nondegenerate(verts, tris - offset)
            vertices.append(verts)
            uvs.append(uv)
            normals.append(_smooth_normals(verts, tris))
            faces.append(tris + offset)
            offset += len(verts)
        if self.cap_ends and self.angle_range is not None:
            outline = np.concatenate([np.asarray(p, dtype=np.float64)[:-1] for p in self.pieces])
            centre = outline.mean(axis=0)
            for angle in (a0, a1):
                ring = np.stack([outline[:, 0] * math.cos(angle), outline[:, 0] * math.sin(angle), outline[:, 1]], -1)
                hub = np.array([[centre[0] * math.cos(angle), centre[0] * math.sin(angle), centre[1]]])
                verts = np.concatenate([hub, ring])
                k = len(ring)
                tris = np.stack([np.zeros(k, dtype=np.int64), 1 + np.arange(k), 1 + (np.arange(k) + 1) % k], -1)
                tris = _nondegenerate(verts, tris)
                vertices.append(verts)
                uvs.append(np.zeros((len(verts), 2)))
                normals.append(_smooth_normals(verts, tris))
                faces.append(tris + offset)
                offset += len(verts)
        return Mesh(
            np.concatenate(vertices),
            np.concatenate(faces).astype(np.int64),
            np.concatenate(uvs),
            np.concatenate(normals),
        )

    def local_surface_distance(self, points: np.ndarray) -> np.ndarray:
        rho = np.hypot(points[:, 0], points[:, 1])
        pieces = [np.asarray(p, dtype=np.float64) for p in self.pieces]
        profile_pts = np.stack([rho, points[:, 2]], axis=-1)
        dist = _polyline_distance_2d(profile_pts, pieces)
        if self.angle_range is None:
            return dist
        a0, a1 = self.angle_range
        phi = np.mod(np.arctan2(points[:, 1], points[:, 0]) - a0, 2.0 * math.pi)
        outside = phi > (a1 - a0) + 1e-9
        if not outside.any():
            return dist
        outline = np.concatenate([p[:-1] for p in pieces])
        end_dist = np.full(int(outside.sum()), np.inf)
        p_out = points[outside]
        for angle in (a0, a1):
            radial = p_out[:, 0] * math.cos(angle) + p_out[:, 1] * math.sin(angle)
            tangential = -p_out[:, 0] * math.sin(angle) + p_out[:, 1] * math.cos(angle)
            in_plane = np.stack([radial, p_out[:, 2]], axis=-1)
            d2 = _polyline_distance_2d(in_plane, pieces)
            if self.cap_ends:
                d2 = np.where(_inside_polygon_2d(in_plane, outline), 0.0, d2)
            end_dist = np.minimum(end_dist, np.hypot(d2, tangential))
        dist = dist.copy()
        dist[outside] = end_dist
        return dist


@dataclass(frozen=True)
class Box:
    """An axis-aligned box centred on the local origin."""

    half_extents: Tuple[float, float, float]
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))

    def local_mesh(self) -> Mesh:
        h = np.asarray(self.half_extents, dtype=np.float64)
        vertices, faces, uvs = [], [], []
        for axis in range(3):
            u_axis, v_axis = (axis + 1) % 3, (axis + 2) % 3
            for sign in (-1.0, 1.0):
                corners = np.zeros((4, 3))
                corners[:, axis] = sign * h[axis]
                corners[:, u_axis] = np.array([-1, 1, 1, -1]) * h[u_axis]
                corners[:, v_axis] = np.array([-1, -1, 1, 1]) * h[v_axis]
                base = len(vertices) * 4
                vertices.append(corners)
                uvs.append(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64))
                faces.append(np.array([[0, 1, 2], [0, 2, 3]]) + base)
        vertices, faces = np.concatenate(vertices), np.concatenate(faces).astype(np.int64)
        return Mesh(vertices, faces, np.concatenate(uvs), _flat_normals(vertices, faces))

    def local_surface_distance(self, points: np.ndarray) -> np.ndarray:
        q = np.abs(points) - np.asarray(self.half_extents)
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        inside = np.minimum(q.max(axis=1), 0.0)
        return np.abs(outside + inside)


@dataclass(frozen=True)
class Quad:
    """A rectangle in the local z = 0 plane; ``uv_tiles`` repeats the texture over it."""

    half_size: Tuple[float, float]
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    uv_tiles: Tuple[float, float] = (1.0, 1.0)
    subdivisions: int = 8

    def local_mesh(self) -> Mesh:
        n = self.subdivisions
        s = np.linspace(0.0, 1.0, n + 1)
        uu, vv = np.meshgrid(s, s, indexing="xy")
        x = (uu * 2.0 - 1.0) * self.half_size[0]
        y = (vv * 2.0 - 1.0) * self.half_size[1]
        verts = np.stack([x, y, np.zeros_like(x)], axis=-1).reshape(-1, 3)
        uv = np.stack([uu * self.uv_tiles[0], vv * self.uv_tiles[1]], axis=-1).reshape(-1, 2)
        idx = np.arange((n + 1) * (n + 1)).reshape(n + 1, n + 1)
        quads = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], axis=-1).reshape(-1, 4)
        tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]).astype(np.int64)
        return Mesh(verts, tris, uv, _flat_normals(verts, tris))

    def local_surface_distance(self, points: np.ndarray) -> np.ndarray:
        dx = np.maximum(np.abs(points[:, 0]) - self.half_size[0], 0.0)
        dy = np.maximum(np.abs(points[:, 1]) - self.half_size[1], 0.0)
        return np.sqrt(dx * dx + dy * dy + points[:, 2] ** 2)


def _object_box(obj) -> Tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (min, max) of a scene object's meshes."""
    verts = np.concatenate([primitive_mesh(p).vertices for part in obj.parts for p in part.primitives])
    return verts.min(axis=0), verts.max(axis=0)


def _nondegenerate(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    tri = vertices[faces]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return faces[area2 > 1e-14]


def _flat_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per-vertex normals for meshes whose faces do not share vertices (boxes, planes)."""
    tri = vertices[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    face_n /= np.linalg.norm(face_n, axis=1, keepdims=True)
    normals = np.zeros_like(vertices)
    for k in range(3):
        normals[faces[:, k]] = face_n
    return normals


def primitive_mesh(primitive) -> Mesh:
    """The primitive's triangle mesh in world coordinates."""
    local = primitive.local_mesh()
    rotation = primitive.pose[:3, :3]
    return Mesh(transform_points(primitive.pose, local.vertices), local.faces, local.uvs, local.normals @ rotation.T)


def primitive_surface_distance(primitive, points_world: np.ndarray) -> np.ndarray:
    """Unsigned distance (metres) from world points to the primitive's ideal surface."""
    local = transform_points(rigid_inverse(primitive.pose), np.asarray(points_world, dtype=np.float64))
    return primitive.local_surface_distance(local)


def _arc(centre: Tuple[float, float], radius: float, start: float, stop: float, n: int) -> np.ndarray:
    t = np.linspace(start, stop, n)
    return np.stack([centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t)], axis=-1)


def sphere(radius: float, pose: np.ndarray) -> Revolved:
    profile = _arc((0.0, 0.0), radius, -math.pi / 2, math.pi / 2, 25)
    profile[:, 0] = np.maximum(profile[:, 0], 0.0)
    return Revolved((profile,), pose=pose, segments=48)


def solid_frustum(r_bottom: float, r_top: float, height: float, pose: np.ndarray, segments: int = 48) -> Revolved:
    """A closed (capped) cone frustum standing on the local z = 0 plane; a cylinder when radii match."""
    pieces = (
        np.array([[0.0, 0.0], [r_bottom, 0.0]]),
        np.array([[r_bottom, 0.0], [r_top, height]]),
        np.array([[r_top, height], [0.0, height]]),
    )
    return Revolved(pieces, pose=pose, segments=segments)


# --------------------------------------------------------------------------------------------
# scene description


@dataclass(frozen=True)
class Material:
    """Diffuse albedo: a flat sRGB colour, or a named texture of the scene (linear values)."""

    srgb: Tuple[int, int, int] = (128, 128, 128)
    texture: Optional[str] = None


@dataclass(frozen=True)
class Part:
    id: int  # 0 for background pieces
    name: str
    primitives: Tuple[object, ...]
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

    def object_surface_distance(self, obj: SceneObject, points_world: np.ndarray) -> np.ndarray:
        return np.min([self.part_surface_distance(part, points_world) for part in obj.parts], axis=0)


# --------------------------------------------------------------------------------------------
# colours and textures

PALETTE: Dict[str, Tuple[int, int, int]] = {
    "red": (200, 40, 40),
    "orange": (235, 130, 30),
    "yellow": (230, 200, 40),
    "green": (60, 160, 60),
    "teal": (30, 150, 150),
    "blue": (40, 80, 200),
    "purple": (130, 60, 170),
    "pink": (230, 120, 170),
    "white": (235, 235, 228),
    "brown": (130, 80, 40),
    "black": (35, 35, 38),
    "grey": (140, 140, 140),
}


def srgb_to_linear(srgb_uint8: np.ndarray) -> np.ndarray:
    c = np.asarray(srgb_uint8, dtype=np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb_uint8(linear: np.ndarray) -> np.ndarray:
    c = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    s = np.where(c <= 0.0031308, c * 12.92, 1.055 * c ** (1.0 / 2.4) - 0.055)
    return np.round(s * 255.0).astype(np.uint8)


def _shade(srgb: Tuple[int, int, int], factor: float) -> Tuple[int, int, int]:
    """Darker (factor < 1) or lighter (factor > 1, towards white) variant of a colour."""
    c = np.asarray(srgb, dtype=np.float64)
    out = c * factor if factor <= 1.0 else c + (255.0 - c) * (factor - 1.0)
    return tuple(int(v) for v in np.clip(np.round(out), 0, 255))


def _value_noise(rng: np.random.Generator, size: Tuple[int, int], cells: int) -> np.ndarray:
    """Smooth tileable noise in [0,1] (bilinear interpolation of a periodic random grid)."""
    h, w = size
    grid = rng.random((cells, cells))
    ys = np.arange(h) * cells / h
    xs = np.arange(w) * cells / w
    y0, x0 = np.floor(ys).astype(int), np.floor(xs).astype(int)
    fy, fx = (ys - y0)[:, None], (xs - x0)[None, :]
    fy, fx = fy * fy * (3 - 2 * fy), fx * fx * (3 - 2 * fx)
    y1, x1 = (y0 + 1) % cells, (x0 + 1) % cells
    a = grid[y0][:, x0]
    b = grid[y0][:, x1]
    c = grid[y1][:, x0]
    d = grid[y1][:, x1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def make_texture(rng: np.random.Generator, size: Tuple[int, int], base_a, base_b, checks: int, dots: int) -> np.ndarray:
    """A feature-rich, tileable albedo texture: two-tone checker, smooth noise and coloured dots."""
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w]
    checker = ((yy * checks // h + xx * checks // w) % 2).astype(bool)
    img = np.where(checker[..., None], np.asarray(base_b, np.float32), np.asarray(base_a, np.float32))
    noise = 0.75 + 0.5 * (0.6 * _value_noise(rng, size, 8) + 0.4 * _value_noise(rng, size, 32))
    img = img * noise[..., None].astype(np.float32)
    for _ in range(dots):
        cy, cx = rng.random(2) * (h, w)
        radius = rng.uniform(0.006, 0.02) * min(h, w)
        colour = rng.uniform(30, 230, size=3)
        reach = int(math.ceil(radius)) + 1
        rows = np.arange(int(cy) - reach, int(cy) + reach + 1)
        cols = np.arange(int(cx) - reach, int(cx) + reach + 1)
        disc = (rows[:, None] - cy) ** 2 + (cols[None, :] - cx) ** 2 <= radius * radius
        window = img[np.ix_(rows % h, cols % w)]
        window[disc] = colour
        img[np.ix_(rows % h, cols % w)] = window
    # stored like an 8-bit sRGB texture file, then linearised for the renderer
    lut = srgb_to_linear(np.arange(256)).astype(np.float32)
    return lut[np.clip(np.round(img), 0, 255).astype(np.uint8)]


# --------------------------------------------------------------------------------------------
# object templates (object-local frame: origin at the bottom centre, z up)


@dataclass(frozen=True)
class Template:
    kind: str
    parts: Tuple[Tuple[str, Tuple[object, ...], Tuple[int, int, int]], ...]  # (name, primitives, srgb)
    footprint_radius: float  # bounding circle on the table, about the local origin
    side: Optional[
        Tuple[str, object]
    ]  # lateral contact shape: ("cylinder", r), ("sphere", r), ("box", (hx, hy, height))
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
        side=("cylinder", r),
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
        side=("box", (hx + e, hy + e, 2 * hz + 2 * ht)),
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
        side=("sphere", r),
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
        side=("cylinder", r),
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
        side=("cylinder", rl),
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
        side=("sphere", r1),
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
# placement


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
    """Horizontal distance from the object's axis to its side surface along a world direction."""
    kind, shape = placed.template.side
    if kind in ("cylinder", "sphere"):
        return float(shape)
    hx, hy, _ = shape
    rel = (direction_yaw - placed.yaw) % (math.pi / 2)
    if min(rel, math.pi / 2 - rel) > 1e-6:
        return None  # a box only offers contact along its face normals
    along_x = abs(math.cos(direction_yaw - placed.yaw)) > 0.5
    return hx if along_x else hy


def _contact_height_ok(a: _Placed, b: _Placed) -> bool:
    """A sphere touches a vertical side only if that side reaches up to the sphere's equator."""
    for sph, other in ((a, b), (b, a)):
        if sph.template.side[0] == "sphere" and other.template.side[0] != "sphere":
            if other.template.side[0] == "box":
                side_height = other.template.side[1][2]
            else:
                side_height = other.template.height * 0.8
            if side_height < sph.template.side[1] + 1e-3:
                return False
    return True


def _touching_pose(rng, anchor: _Placed, template: Template) -> Optional[np.ndarray]:
    if anchor.template.side is None or template.side is None:
        return None
    kind_a, kind_b = anchor.template.side[0], template.side[0]
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
        distance = 2.0 * math.sqrt(anchor.template.side[1] * template.side[1])
    else:
        distance = sa + sb
    xy = anchor.xy + distance * np.array([math.cos(direction), math.sin(direction)])
    pose = translate(xy[0], xy[1], anchor.pose[2, 3]) @ rot_z(yaw_b)
    candidate.pose = pose
    if not _contact_height_ok(anchor, candidate):
        return None
    return pose


def _place_objects(
    rng: np.random.Generator,
    kinds: Sequence[str],
    sizes: Sequence[float],
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
            if clear:
                item.pose, item.on_table = pose, False
                touching = [t for t in touching if i not in t] + [(j, i)]
    return touching


def _stack_on(rng, base: _Placed, template: Template) -> Optional[np.ndarray]:
    """Pose resting a ball on the flat top of ``base`` (the two touch at one point)."""
    if base.template.top is None or template.kind != "ball":
        return None
    hx, hy, top_z = base.template.top
    r = template.side[1]
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
            parts.append(Part(part_id, name, world_prims, Material(srgb=tuple(int(c) for c in srgb))))
            part_id += 1
        interior = transform_points(item.pose, np.asarray(item.template.interior_point)[None])[0]
        name = item.template.kind if item.template.kind in _SELF_COLOURED else f"{item.colour} {item.template.kind}"
        objects.append(SceneObject(index + 1, name, item.template.kind, item.colour, tuple(parts), interior))
    return tuple(objects)


_SELF_COLOURED = {"orange", "lime", "lemon", "plum"}


# --------------------------------------------------------------------------------------------
# cameras


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world [4,4] in OpenCV convention for a camera at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    forward = target - eye
    norm = np.linalg.norm(forward)
    if norm == 0.0:
        raise ValueError("look_at: eye and target coincide; place the camera away from its target")
    forward /= norm
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to 'up'; pick another up vector")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
    return c2w


def _interleaved_eval(total: int, num_eval: int) -> Tuple[int, ...]:
    if num_eval <= 0:
        return ()
    return tuple(int(i) for i in np.round((np.arange(num_eval) + 0.5) * total / num_eval - 0.5).astype(int))


def _ring_cameras(rng, total, radius, elevation_range, target, jitter=0.03) -> List[Camera]:
    """Views around the scene: golden-angle azimuths over an elevation band, so any subset is spread out."""
    golden = math.pi * (3.0 - math.sqrt(5.0))
    cams = []
    lo, hi = elevation_range
    for i in range(total):
        azimuth = i * golden + rng.uniform(-0.05, 0.05)
        frac = (i + 0.5) / total
        elevation = math.radians(lo + (hi - lo) * (0.5 + 0.5 * math.sin(2.0 * math.pi * 3.0 * frac)))
        dist = radius * (1.0 + rng.uniform(-jitter, jitter))
        eye = np.array(
            [
                dist * math.cos(elevation) * math.cos(azimuth),
                dist * math.cos(elevation) * math.sin(azimuth),
                dist * math.sin(elevation),
            ]
        ) + np.asarray(target)
        aim = np.asarray(target) + rng.uniform(-0.015, 0.015, size=3)
        cams.append(Camera(look_at(eye, aim)))
    return cams


def _framing(objects: Sequence[SceneObject], intrinsics: Intrinsics, margin: float = 0.85) -> Tuple[np.ndarray, float]:
    """Look-at target and camera distance that keep every object's bounding sphere inside the view."""
    verts = np.concatenate(
        [primitive_mesh(p).vertices for obj in objects for part in obj.parts for p in part.primitives]
    )
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    target = np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, 0.4 * hi[2]])
    radius = float(np.max(np.linalg.norm(verts - target, axis=1)))
    half_fov = min(
        math.atan(intrinsics.width / (2 * intrinsics.fx)), math.atan(intrinsics.height / (2 * intrinsics.fy))
    )
    return target, radius / math.sin(margin * half_fov)


def _intrinsics(width: int, height: int, fov_x_degrees: float) -> Intrinsics:
    if width < 8 or height < 8:
        raise ValueError(f"image size {width}x{height} is too small; use at least 8x8 pixels")
    fx = width / (2.0 * math.tan(math.radians(fov_x_degrees) / 2.0))
    return Intrinsics(width, height, fx, fx, width / 2.0, height / 2.0)


# --------------------------------------------------------------------------------------------
# recipes


def _room_background(rng_tex, ground_half: float, wall_radius: float, wall_height: float, plain_colours=None):
    """Table plane and a cylindrical wall: textured, or flat ``(table, wall)`` sRGB colours."""
    if plain_colours is None:
        ground_tex = make_texture(rng_tex, (256, 256), (180, 150, 110), (150, 120, 85), checks=8, dots=60)
        wall_tex = make_texture(rng_tex, (256, 512), (120, 135, 150), (95, 110, 125), checks=6, dots=90)
        materials, textures = (
            (Material(texture="table"), Material(texture="wall")),
            {"table": ground_tex, "wall": wall_tex},
        )
    else:
        materials, textures = (Material(srgb=plain_colours[0]), Material(srgb=plain_colours[1])), {}
    ground = Part(0, "table", (Quad((ground_half, ground_half), uv_tiles=(ground_half, ground_half)),), materials[0])
    wall_profile = np.array([[wall_radius, 0.0], [wall_radius, wall_height]])
    wall = Part(0, "wall", (Revolved((wall_profile,), segments=96),), materials[1])
    return (ground, wall), textures


def _lighting(rng_light) -> Lighting:
    azimuth = rng_light.uniform(0.0, 2.0 * math.pi)
    elevation = math.radians(rng_light.uniform(50.0, 65.0))
    toward_sun = np.array(
        [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
    )
    return Lighting(tuple(float(v) for v in -toward_sun), sun_irradiance=1.9, ambient_radiance=0.38)


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
    count = int(rng.integers(6, 13)) if num_objects is None else int(num_objects)
    if not 1 <= count <= len(PALETTE):
        raise ValueError(f"num_objects must be between 1 and {len(PALETTE)} (got {count})")
    kinds = _pick_kinds(rng, count, list(TABLETOP_KINDS))
    colours = [str(c) for c in rng.permutation(list(PALETTE))[:count]]
    sizes = rng.uniform(1.1, 1.6, size=count)
    table_radius = 0.32 + 0.025 * count

    def inside(xy, r):
        return np.linalg.norm(xy) + r <= table_radius

    def sample_xy(index=0):
        rho = table_radius * math.sqrt(rng.random())
        phi = rng.uniform(0.0, 2.0 * math.pi)
        return np.array([rho * math.cos(phi), rho * math.sin(phi)])

    placed, touching = _place_objects(rng, kinds, sizes, colours, inside, sample_xy, 0.35, min(1, count - 1))
    touching = _rest_balls_on_tops(rng, placed, touching)
    objects = _build_objects(placed)
    background, textures = _room_background(np.random.default_rng([seed, _STREAM_TEXTURES]), 3.0, 2.8, 1.8)
    total = num_views + num_eval_views
    intrinsics = _intrinsics(width, height, fov_x_degrees)
    target, distance = _framing(objects, intrinsics)
    cameras = _ring_cameras(np.random.default_rng([seed, _STREAM_CAMERAS]), total, distance, (22.0, 50.0), target)
    return Scene(
        recipe="tabletop360",
        seed=seed,
        objects=objects,
        background=background,
        textures=textures,
        cameras=tuple(cameras),
        eval_indices=_interleaved_eval(total, num_eval_views),
        intrinsics=intrinsics,
        lighting=_lighting(np.random.default_rng([seed, _STREAM_LIGHTS])),
        touching=tuple(sorted((a + 1, b + 1) for a, b in touching)),
        parameters=dict(
            num_objects=count, table_radius=table_radius, camera_distance=distance, camera_target=target.tolist()
        ),
    )


def _fruit(kind: str, radius: float):
    def build(rng, s, colour):
        r = radius * s * rng.uniform(0.9, 1.1)
        parts = [("body", (sphere(r, translate(0.0, 0.0, r)),), colour)]
        height = 2 * r
        if kind == "apple":
            stem = solid_frustum(0.1 * r, 0.07 * r, 0.45 * r, translate(0.0, 0.0, 1.85 * r), segments=12)
            parts.append(("stem", (stem,), PALETTE["brown"]))
            height = 2.3 * r
        return Template(kind, tuple(parts), r, ("sphere", r), None, None, (0.0, 0.0, r), height)

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
        rf = tmpl.side[1]
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

    def inside(xy, r):
        return np.linalg.norm(xy) + r <= table_radius

    def sample_xy(index=0):
        rho = table_radius * math.sqrt(rng.random())
        phi = rng.uniform(0.0, 2.0 * math.pi)
        return np.array([rho * math.cos(phi), rho * math.sin(phi)])

    placed = [bowl] + fruits
    rest, rest_touching = _place_objects_after(
        rng, placed, kinds, rng.uniform(1.1, 1.4, size=extra), colours, inside, sample_xy
    )
    all_placed = placed + rest
    touching = [(0, 1 + i) for i in range(len(fruits))] + rest_touching
    objects = _build_objects(all_placed)
    background, textures = _room_background(np.random.default_rng([seed, _STREAM_TEXTURES]), 3.0, 2.8, 1.8)
    total = num_views + num_eval_views
    intrinsics = _intrinsics(width, height, fov_x_degrees)
    target, distance = _framing(objects, intrinsics)
    cameras = _ring_cameras(np.random.default_rng([seed, _STREAM_CAMERAS]), total, distance, (32.0, 62.0), target)
    return Scene(
        recipe="nested",
        seed=seed,
        objects=objects,
        background=background,
        textures=textures,
        cameras=tuple(cameras),
        eval_indices=_interleaved_eval(total, num_eval_views),
        intrinsics=intrinsics,
        lighting=_lighting(np.random.default_rng([seed, _STREAM_LIGHTS])),
        touching=tuple(sorted((a + 1, b + 1) for a, b in touching)),
        parameters=dict(num_objects=len(objects), bowl_instance=1, fruit_instances=[2 + i for i in range(len(fruits))]),
    )


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


def _forward_background(rng_tex, plain_colours: Optional[Tuple[Tuple[int, int, int], Tuple[int, int, int]]] = None):
    """Ground and back wall of a forward-facing capture: textured, or flat ``(ground, wall)`` sRGB colours."""
    if plain_colours is None:
        ground_tex = make_texture(rng_tex, (256, 256), (170, 160, 120), (140, 130, 95), checks=8, dots=70)
        wall_tex = make_texture(rng_tex, (256, 512), (150, 120, 120), (120, 95, 100), checks=6, dots=120)
        materials, textures = (
            (Material(texture="ground"), Material(texture="wall")),
            {"ground": ground_tex, "wall": wall_tex},
        )
    else:
        materials, textures = (Material(srgb=plain_colours[0]), Material(srgb=plain_colours[1])), {}
    ground = Part(0, "ground", (Quad((4.5, 4.0), pose=translate(0.0, 2.5, 0.0), uv_tiles=(9.0, 8.0)),), materials[0])
    wall = Part(
        0,
        "wall",
        (Quad((4.5, 1.8), pose=translate(0.0, 5.5, 1.8) @ rot_x(math.pi / 2), uv_tiles=(3.0, 1.2)),),
        materials[1],
    )
    return (ground, wall), textures


def _forward_cameras(cam_rng, total: int) -> List[Camera]:
    """A grid of views on a 0.6 x 0.25 m vertical patch at y = 0, all looking +y and 14 degrees down."""
    cols = max(1, int(math.ceil(math.sqrt(total * 1.5))))
    rows = int(math.ceil(total / cols))
    cameras = []
    pitch = math.radians(-14.0)
    for i in range(total):
        r, c = divmod(i, cols)
        x = -0.3 + 0.6 * (c + 0.5) / cols + cam_rng.uniform(-0.02, 0.02)
        z = 0.75 - 0.25 * (r + 0.5) / rows + cam_rng.uniform(-0.02, 0.02)
        yaw = cam_rng.uniform(-0.03, 0.03)
        direction = np.array([math.sin(yaw) * math.cos(pitch), math.cos(yaw) * math.cos(pitch), math.sin(pitch)])
        eye = np.array([x, 0.0, z])
        cameras.append(Camera(look_at(eye, eye + direction)))
    return cameras


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
    count = int(rng.integers(6, 10)) if num_objects is None else int(num_objects)
    if not 1 <= count <= len(PALETTE):
        raise ValueError(f"num_objects must be between 1 and {len(PALETTE)} (got {count})")
    kinds = _pick_kinds(rng, count, list(TABLETOP_KINDS))
    colours = [str(c) for c in rng.permutation(list(PALETTE))[:count]]
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
    background, textures = _forward_background(np.random.default_rng([seed, _STREAM_TEXTURES]))
    total = num_views + num_eval_views
    cameras = _forward_cameras(np.random.default_rng([seed, _STREAM_CAMERAS]), total)
    return Scene(
        recipe="forward",
        seed=seed,
        objects=objects,
        background=background,
        textures=textures,
        cameras=tuple(cameras),
        eval_indices=_interleaved_eval(total, num_eval_views),
        intrinsics=_intrinsics(width, height, fov_x_degrees),
        lighting=_lighting(np.random.default_rng([seed, _STREAM_LIGHTS])),
        touching=tuple(sorted((a + 1, b + 1) for a, b in touching)),
        parameters=dict(num_objects=count, depth_range=[near, far]),
    )


# --------------------------------------------------------------------------------------------
# the randomised family (votesplat_ns/eval/synthetic/family.py names its tuning and test seeds)

_STREAM_FAMILY = 6
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
        side=("box", (hx, hy, 2 * hz)),
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


def _rings_cameras(rng, total: int, distance: float, elevations: Sequence[float], target, jitter: float = 0.03):
    """Views on one ring per elevation (degrees), each ring a consecutive block of views so that interleaved
    held-out views fall on every ring; golden-angle azimuths within a ring. Returns (cameras, ring of each view)."""
    golden = math.pi * (3.0 - math.sqrt(5.0))
    n = len(elevations)
    start = rng.uniform(0.0, 2.0 * math.pi)
    cams, rings = [], []
    for i in range(total):
        ring = min(n - 1, i * n // total)
        k = i - (-(-ring * total // n))  # index within the ring
        azimuth = start + 0.9 * ring + k * golden + rng.uniform(-0.05, 0.05)
        elevation = math.radians(elevations[ring] + rng.uniform(-1.5, 1.5))
        dist = distance * (1.0 + rng.uniform(-jitter, jitter))
        eye = np.array(
            [
                dist * math.cos(elevation) * math.cos(azimuth),
                dist * math.cos(elevation) * math.sin(azimuth),
                dist * math.sin(elevation),
            ]
        ) + np.asarray(target)
        aim = np.asarray(target) + rng.uniform(-0.015, 0.015, size=3)
        cams.append(Camera(look_at(eye, aim)))
        rings.append(ring)
    return cams, rings


def surface_samples(obj: SceneObject, count: int = 2000) -> np.ndarray:
    """``count`` area-uniform points on an object's surface (fixed sampling; for framing checks)."""
    meshes = [primitive_mesh(p) for part in obj.parts for p in part.primitives]
    tris = np.concatenate([m.vertices[m.faces] for m in meshes])
    areas = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    rng = np.random.default_rng(0)
    pick = rng.choice(len(tris), size=count, p=areas / areas.sum())
    r1, r2 = rng.random(count), rng.random(count)
    flip = r1 + r2 > 1.0
    r1[flip], r2[flip] = 1.0 - r1[flip], 1.0 - r2[flip]
    t = tris[pick]
    return t[:, 0] + r1[:, None] * (t[:, 1] - t[:, 0]) + r2[:, None] * (t[:, 2] - t[:, 0])


def frame_overflow(
    camera: Camera, intrinsics: Intrinsics, points: np.ndarray, margin: float = 0.0
) -> Tuple[float, bool]:
    """(share of ``points`` that project into the image, whether others fall outside it or behind the camera);
    ``margin``: a border of this share of the image width that counts as outside."""
    viewmat = camera.viewmat
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    front = z > 1e-6
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intrinsics.fx * cam[:, 0] / z + intrinsics.cx
        v = intrinsics.fy * cam[:, 1] / z + intrinsics.cy
    m = margin * intrinsics.width
    inside = front & (u >= m) & (u <= intrinsics.width - m) & (v >= m) & (v <= intrinsics.height - m)
    return float(inside.mean()), bool((~inside).any())


def cut_view_share(
    cameras: Sequence[Camera], intrinsics: Intrinsics, points: np.ndarray, min_visible: float = 0.05
) -> float:
    """Share of views that see at least ``min_visible`` of the points while others overflow the frame."""
    cut = 0
    for camera in cameras:
        visible, overflows = frame_overflow(camera, intrinsics, points)
        cut += visible >= min_visible and overflows
    return cut / max(1, len(cameras))


def _camera_clear(cameras: Sequence[Camera], boxes: Sequence[Tuple[np.ndarray, np.ndarray]], clearance: float) -> bool:
    for camera in cameras:
        eye = camera.c2w[:3, 3]
        if eye[2] < 0.03:
            return False
        for lo, hi in boxes:
            if np.linalg.norm(np.maximum(0.0, np.maximum(lo - eye, eye - hi))) < clearance:
                return False
    return True


def _place_on_top(
    rng, placed: List[_Placed], base_index: int, items, touching: List[Tuple[int, int]], margin: float = 0.01
):
    """Stand ``items`` ((kind, size, colour) ...) on the flat top of ``placed[base_index]``, apart from each other.

    Each one placed touches the base; one that finds no room is left out.
    """
    base = placed[base_index]
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
    hx_b, hy_b, top_z = base.template.top
    # _box's half extents are at most 0.078 s and 0.065 s
    size = 0.85 * min(hx_b / 0.078, hy_b / 0.065)
    template = _box(rng, size, PALETTE[colour])
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


def _plain_colours(rng_tex) -> Tuple[Tuple[int, int, int], Tuple[int, int, int]]:
    """Flat (ground, wall) sRGB colours: a light ground and a wall of another hue."""
    ground = tuple(int(v) for v in rng_tex.uniform(150, 215, size=3))
    wall = tuple(int(v) for v in rng_tex.uniform(110, 200, size=3))
    return ground, wall


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

        def inside(xy, r):
            return np.linalg.norm(xy) + r <= radius

        def sample_xy(index=0):
            rho = radius * math.sqrt(rng.random())
            phi = rng.uniform(0.0, 2.0 * math.pi)
            return np.array([rho * math.cos(phi), rho * math.sin(phi)])

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
        background, textures = _forward_background(rng_tex, plain)
    else:
        background, textures = _room_background(
            rng_tex, room["ground_half"], room["wall_radius"], room["wall_height"], plain
        )
    large = [o.id for o in objects if o.kind in ("monitor", "table", "board", "carton")]
    parameters.update(
        properties=asdict(props),
        property_kinds=list(props.kinds),
        num_objects=len(objects),
        large_instances=large,
        cut_instance=objects[0].id if props.cut_object is not None else None,
    )
    return Scene(
        recipe="family",
        seed=seed,
        objects=objects,
        background=background,
        textures=textures,
        cameras=tuple(cameras),
        eval_indices=_interleaved_eval(total, num_eval_views),
        intrinsics=intrinsics,
        lighting=_lighting(np.random.default_rng([seed, _STREAM_LIGHTS])),
        touching=tuple(sorted((min(a, b) + 1, max(a, b) + 1) for a, b in touching)),
        parameters=parameters,
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
