"""Pictures of a view's masks and 2D votes (paper §3.2): each level's masks tinted, each centroid a cross."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from votesplat_ns.core.vote_cache import atomic_write_bytes
from votesplat_ns.core.vote_maps import VoteMaps


def _label_colours(count: int) -> np.ndarray:
    """Distinct deterministic colours (golden-ratio hues), uint8 [count, 3]; row 0 black."""
    hues = (np.arange(count) * 0.61803398875) % 1.0
    hsv = np.stack([hues * 179, np.full(count, 200), np.full(count, 255)], axis=-1).astype(np.uint8)
    colours = cv2.cvtColor(hsv[None], cv2.COLOR_HSV2RGB)[0]
    colours[0] = 0
    return colours


def render_vote_preview(image: np.ndarray, vote_maps: VoteMaps) -> np.ndarray:
    """One panel per level, side by side: image with masks tinted and each centroid marked by a cross."""
    height, width = vote_maps.height, vote_maps.width
    if image.shape[:2] != (height, width):
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    marker = max(5, min(height, width) // 30)
    panels = []
    for level in range(vote_maps.num_levels):
        labels = np.asarray(vote_maps.labels[level]).astype(np.int64)
        table = vote_maps.centroids[level]
        colours = _label_colours(table.shape[0])
        inside = labels > 0
        panel = image.astype(np.float32)
        panel[inside] = 0.45 * panel[inside] + 0.55 * colours[labels[inside]]
        panel = np.ascontiguousarray(panel.clip(0, 255).astype(np.uint8))
        for k in range(1, table.shape[0]):
            if not np.all(np.isfinite(table[k])):
                continue
            centre = (int(round(float(table[k, 0]))), int(round(float(table[k, 1]))))
            cv2.drawMarker(panel, centre, (0, 0, 0), cv2.MARKER_CROSS, marker, 3)
            cv2.drawMarker(panel, centre, tuple(int(c) for c in colours[k]), cv2.MARKER_CROSS, marker, 1)
        if width >= 160:  # a caption would cover a tiny image
            name = vote_maps.level_names[level] if vote_maps.level_names else str(level)
            scale = width / 640
            origin = (4, 4 + int(24 * scale))
            text = f"{name}: {table.shape[0] - 1} masks"
            cv2.putText(panel, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), max(2, int(4 * scale)))
            cv2.putText(panel, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), max(1, int(1.5 * scale)))
        panels.append(panel)
        panels.append(np.full((height, 3, 3), 255, dtype=np.uint8))
    return np.concatenate(panels[:-1], axis=1)


def write_png(path: Path, image_rgb: np.ndarray) -> None:
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"could not encode preview {path}")
    atomic_write_bytes(path, lambda handle: handle.write(encoded.tobytes()))
