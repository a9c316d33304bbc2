"""Rigid transforms and the primitives scenes are made of: each knows its own triangle mesh and an
analytic distance to its ideal surface."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Sequence, Tuple, Union

import numpy as np

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

    def local_inside(self, points: np.ndarray) -> np.ndarray:
        """Points inside the solid: only for a full sweep of a profile that is closed (its ends meet,
        or both lie on the axis); an open profile (a bowl, a lampshade) encloses no volume."""
        pieces = [np.asarray(p, dtype=np.float64) for p in self.pieces]
        outline = np.concatenate([pieces[0]] + [p[1:] for p in pieces[1:]])
        ends_meet = np.allclose(outline[0], outline[-1])
        ends_on_axis = abs(outline[0, 0]) < 1e-9 and abs(outline[-1, 0]) < 1e-9
        if self.angle_range is not None or not (ends_meet or ends_on_axis):
            return np.zeros(len(points), dtype=bool)
        if ends_on_axis:  # exactly on it, so that a point on the axis is not counted across the closing edge
            outline[[0, -1], 0] = 0.0
        rho = np.hypot(points[:, 0], points[:, 1])
        return _inside_polygon_2d(np.stack([rho, points[:, 2]], axis=-1), outline)


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

    def local_inside(self, points: np.ndarray) -> np.ndarray:
        return (np.abs(points) <= np.asarray(self.half_extents)).all(axis=1)


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

    def local_inside(self, points: np.ndarray) -> np.ndarray:
        return np.zeros(len(points), dtype=bool)  # a sheet encloses nothing


# What a part is made of: a surface with a pose in the part's frame.
Primitive = Union[Revolved, Box, Quad]


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


def primitive_solid_distance(primitive, points_world: np.ndarray) -> np.ndarray:
    """Distance (metres) from world points to the primitive's solid: 0 inside a closed primitive,
    the distance to its surface elsewhere."""
    local = transform_points(rigid_inverse(primitive.pose), np.asarray(points_world, dtype=np.float64))
    return np.where(primitive.local_inside(local), 0.0, primitive.local_surface_distance(local))


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
