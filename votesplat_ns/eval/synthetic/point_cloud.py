"""The dataset's sparse point cloud: surface points seen by >= 2 training views (an SfM stand-in)."""

from __future__ import annotations

from typing import Sequence, Tuple

import numpy as np

from votesplat_ns.eval.synthetic.scenes import Part, Scene, linear_to_srgb_uint8, primitive_mesh


def _sample_surface(rng, parts: Sequence[Part], textures, count: int) -> Tuple[np.ndarray, np.ndarray]:
    """``count`` area-uniform points on the parts' meshes with their albedo as sRGB uint8."""
    meshes = [(part, primitive_mesh(p)) for part in parts for p in part.primitives]
    areas = []
    for _, mesh in meshes:
        tri = mesh.vertices[mesh.faces]
        areas.append(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1))
    total = np.concatenate(areas)
    choice = rng.choice(len(total), size=count, p=total / total.sum())
    offsets = np.cumsum([0] + [len(a) for a in areas])
    r1, r2 = rng.random(count), rng.random(count)
    swap = r1 + r2 > 1.0
    r1[swap], r2[swap] = 1.0 - r1[swap], 1.0 - r2[swap]
    points = np.zeros((count, 3))
    colours = np.zeros((count, 3), dtype=np.uint8)
    for m, (part, mesh) in enumerate(meshes):
        sel = np.nonzero((choice >= offsets[m]) & (choice < offsets[m + 1]))[0]
        if len(sel) == 0:
            continue
        faces = mesh.faces[choice[sel] - offsets[m]]
        a, b, c = (mesh.vertices[faces[:, k]] for k in range(3))
        points[sel] = a + r1[sel, None] * (b - a) + r2[sel, None] * (c - a)
        if part.material.texture is None:
            colours[sel] = part.material.srgb
        else:
            ua, ub, uc = (mesh.uvs[faces[:, k]] for k in range(3))
            uv = ua + r1[sel, None] * (ub - ua) + r2[sel, None] * (uc - ua)
            tex = textures[part.material.texture]
            th, tw = tex.shape[:2]
            # mitsuba samples bitmaps with v = 0 at the first (top) row
            col = np.floor(np.mod(uv[:, 0], 1.0) * tw).astype(int) % tw
            row = np.floor(np.mod(uv[:, 1], 1.0) * th).astype(int) % th
            colours[sel] = linear_to_srgb_uint8(tex[row, col])
    return points, colours


def _visible_count(points: np.ndarray, scene: Scene, depths: Sequence[np.ndarray], views: Sequence[int]) -> np.ndarray:
    intr = scene.intrinsics
    counts = np.zeros(len(points), dtype=np.int64)
    for view in views:
        viewmat = scene.cameras[view].viewmat
        cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = intr.fx * cam[:, 0] / z + intr.cx
            v = intr.fy * cam[:, 1] / z + intr.cy
        ok = (z > 1e-3) & (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)
        x = np.clip(np.floor(np.nan_to_num(u)).astype(int), 0, intr.width - 1)
        y = np.clip(np.floor(np.nan_to_num(v)).astype(int), 0, intr.height - 1)
        d = depths[view][y, x]
        # a point hidden behind a nearer surface reads a smaller depth at its pixel
        ok &= (d > 0) & (z <= d + np.maximum(0.01, 0.01 * d))
        counts += ok
    return counts


def sparse_point_cloud(scene: Scene, depths: Sequence[np.ndarray], num_points: int = 4000, seed: int = 0):
    """SfM stand-in: surface points (half on objects, half on the background) seen by >= 2 training views."""
    rng = np.random.default_rng([scene.seed, 5, seed])
    train = [i for i in range(len(scene.cameras)) if i not in set(scene.eval_indices)]
    min_views = 2 if len(train) >= 2 else 1
    chosen_pts, chosen_cols = [], []
    object_parts = [part for _, part in scene.parts]
    for parts, budget in ((object_parts, num_points // 2), (list(scene.background), num_points - num_points // 2)):
        if not parts or budget <= 0:
            continue
        kept_pts, kept_cols, have = [], [], 0
        # most of a large background is out of every view: draw bigger batches until the budget is met
        for round_index in range(8):
            pts, cols = _sample_surface(rng, parts, scene.textures, budget * 4 * 2**round_index)
            keep = np.nonzero(_visible_count(pts, scene, depths, train) >= min_views)[0][: budget - have]
            kept_pts.append(pts[keep])
            kept_cols.append(cols[keep])
            have += len(keep)
            if have >= budget:
                break
        chosen_pts += kept_pts
        chosen_cols += kept_cols
    return np.concatenate(chosen_pts), np.concatenate(chosen_cols)
