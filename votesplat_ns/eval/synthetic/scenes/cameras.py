"""Cameras: look-at poses, rings around the scene, forward-facing grids, framing and the checks of how
an object fills the frame."""

from __future__ import annotations

import math
from typing import List, Sequence, Tuple

import numpy as np
from numpy.typing import ArrayLike

from votesplat_ns.eval.synthetic.scenes.description import Camera, Intrinsics, SceneObject
from votesplat_ns.eval.synthetic.scenes.primitives import primitive_mesh


def look_at(eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world [4,4] in OpenCV convention for a camera at ``eye`` looking at ``target``."""
    eye_at, target_at, up_along = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    forward = target_at - eye_at
    norm = np.linalg.norm(forward)
    if norm == 0.0:
        raise ValueError("look_at: eye and target coincide; place the camera away from its target")
    forward /= norm
    right = np.cross(forward, up_along)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to 'up'; pick another up vector")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye_at
    return c2w


def _interleaved_eval(total: int, num_eval: int) -> Tuple[int, ...]:
    if num_eval <= 0:
        return ()
    return tuple(int(i) for i in np.round((np.arange(num_eval) + 0.5) * total / num_eval - 0.5).astype(int))


def _orbit_camera(rng, target, distance: float, azimuth: float, elevation: float, jitter: float) -> Camera:
    """A view of ``target`` from ``distance`` (jittered by up to ``jitter`` of it) at ``azimuth`` and ``elevation``
    (radians), aimed within 1.5 cm of the target."""
    dist = distance * (1.0 + rng.uniform(-jitter, jitter))
    eye = np.array(
        [
            dist * math.cos(elevation) * math.cos(azimuth),
            dist * math.cos(elevation) * math.sin(azimuth),
            dist * math.sin(elevation),
        ]
    ) + np.asarray(target)
    aim = np.asarray(target) + rng.uniform(-0.015, 0.015, size=3)
    return Camera(look_at(eye, aim))


def _ring_cameras(rng, total, radius, elevation_range, target, jitter=0.03) -> List[Camera]:
    """Views around the scene: golden-angle azimuths over an elevation band, so any subset is spread out."""
    golden = math.pi * (3.0 - math.sqrt(5.0))
    cams = []
    lo, hi = elevation_range
    for i in range(total):
        azimuth = i * golden + rng.uniform(-0.05, 0.05)
        frac = (i + 0.5) / total
        elevation = math.radians(lo + (hi - lo) * (0.5 + 0.5 * math.sin(2.0 * math.pi * 3.0 * frac)))
        cams.append(_orbit_camera(rng, target, radius, azimuth, elevation, jitter))
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
        cams.append(_orbit_camera(rng, target, distance, azimuth, elevation, jitter))
        rings.append(ring)
    return cams, rings


# --------------------------------------------------------------------------------------------
# how an object fills the frame (the family recipe's cut object)


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
