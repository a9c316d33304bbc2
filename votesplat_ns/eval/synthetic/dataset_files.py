"""The files of a synthetic dataset: atomic writers, depth and frame-name encodings, the camera
convention of transforms.json, and the readers. numpy and Pillow only, never mitsuba (the layout is
described in :mod:`votesplat_ns.eval.synthetic.render`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Callable, List, Tuple

import numpy as np

from votesplat_ns.core.ply_io import atomic_write
from votesplat_ns.eval.synthetic.scenes import GENERATOR_VERSION, Scene, make_scene

DEPTH_UNIT_METRES = 1e-3
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


# --------------------------------------------------------------------------------------------
# atomic writers


def _atomic_write_bytes(path: Path, write: Callable[[BinaryIO], None]) -> None:
    """``write(handle)`` fills a binary file that replaces ``path`` in one rename (``ply_io.atomic_write``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "wb") as handle:
        write(handle)


def write_png(path: Path, array: np.ndarray) -> None:
    """Atomic PNG write: uint8 [H,W,3] RGB, or uint16 [H,W] single channel (16-bit PNG)."""
    from PIL import Image

    array = np.ascontiguousarray(array)
    if array.dtype == np.uint16 and array.ndim == 2:
        image = Image.fromarray(array)
    elif array.dtype == np.uint8 and array.ndim in (2, 3):
        image = Image.fromarray(array)
    else:
        raise ValueError(f"write_png: expected uint8 [H,W(,3)] or uint16 [H,W], got {array.dtype} {array.shape}")
    _atomic_write_bytes(path, lambda handle: image.save(handle, format="PNG"))


def write_jpeg(path: Path, rgb: np.ndarray, quality: int) -> None:
    """Atomic JPEG write of uint8 [H,W,3] RGB, without chroma subsampling (object edges keep their colour)."""
    from PIL import Image

    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"write_jpeg: expected uint8 [H,W,3], got {rgb.dtype} {rgb.shape}")
    image = Image.fromarray(np.ascontiguousarray(rgb))
    _atomic_write_bytes(path, lambda handle: image.save(handle, format="JPEG", quality=int(quality), subsampling=0))


def write_json(path: Path, data: dict) -> None:
    payload = (json.dumps(data, indent=2) + "\n").encode("utf-8")

    def write(handle: BinaryIO) -> None:
        handle.write(payload)

    _atomic_write_bytes(path, write)


def write_point_ply(path: Path, points: np.ndarray, colours_uint8: np.ndarray) -> None:
    """Binary PLY with float x,y,z and uchar red,green,blue (what nerfstudio's loader, via open3d, reads)."""
    from plyfile import PlyData, PlyElement

    vertex = np.zeros(
        len(points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    )
    vertex["x"], vertex["y"], vertex["z"] = np.asarray(points, dtype=np.float32).T
    vertex["red"], vertex["green"], vertex["blue"] = np.asarray(colours_uint8, dtype=np.uint8).T
    data = PlyData([PlyElement.describe(vertex, "vertex")], text=False)
    _atomic_write_bytes(path, data.write)


def encode_depth_mm(depth_m: np.ndarray) -> np.ndarray:
    """Metres -> uint16 millimetres; 0 (invalid) where there is no surface or it is beyond 65.535 m."""
    mm = np.round(np.asarray(depth_m, dtype=np.float64) / DEPTH_UNIT_METRES)
    mm[(mm <= 0) | (mm > np.iinfo(np.uint16).max) | ~np.isfinite(mm)] = 0
    return mm.astype(np.uint16)


def frame_name(index: int, extension: str = "png") -> str:
    return f"frame_{index + 1:05d}.{extension}"


# --------------------------------------------------------------------------------------------
# camera convention


def opencv_c2w_to_nerfstudio(c2w: np.ndarray) -> np.ndarray:
    """Camera-to-world in OpenCV convention -> nerfstudio/OpenGL convention (x right, y up, looks along -z)."""
    return np.asarray(c2w, dtype=np.float64) @ OPENCV_TO_OPENGL


def nerfstudio_to_opencv_c2w(transform_matrix) -> np.ndarray:
    m = np.asarray(transform_matrix, dtype=np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    return m @ OPENCV_TO_OPENGL


# --------------------------------------------------------------------------------------------
# reading


def read_label_png(path) -> np.ndarray:
    """A 16-bit (or 8-bit) single-channel label/depth PNG as an integer array [H,W]."""
    from PIL import Image

    with Image.open(path) as image:
        if image.mode not in ("I;16", "I;16B", "I", "L"):
            raise ValueError(f"{path}: expected a single-channel 8/16-bit PNG, got mode {image.mode}")
        return np.array(image)


def read_depth_png(path) -> np.ndarray:
    """Depth PNG -> metres (float64), 0 where invalid."""
    return read_label_png(path).astype(np.float64) * DEPTH_UNIT_METRES


@dataclass(frozen=True)
class DatasetView:
    name: str
    c2w: np.ndarray  # OpenCV camera-to-world
    viewmat: np.ndarray  # OpenCV world-to-camera
    K: np.ndarray
    is_eval: bool


def scene_from_dataset(meta: dict) -> Scene:
    """Rebuild the generating scene (exact geometry, no rendering) from a dataset's transforms.json."""
    info = meta.get("votesplat_synthetic")
    if info is None:
        raise ValueError("transforms.json has no 'votesplat_synthetic' entry; it was not written by votesplat synth")
    if info.get("generator_version") != GENERATOR_VERSION:
        raise ValueError(
            f"dataset made by generator version {info.get('generator_version')}, this is {GENERATOR_VERSION}; regenerate it"
        )
    return make_scene(info["recipe"], seed=int(info["seed"]), **info["scene_options"])


def read_views(dataset_dir) -> Tuple[dict, List[DatasetView]]:
    """transforms.json and the cameras in OpenCV convention (in the dataset's own world frame)."""
    dataset_dir = Path(dataset_dir)
    path = dataset_dir / "transforms.json"
    if not path.exists():
        raise ValueError(f"{path} not found; point at a folder written by votesplat synth")
    meta = json.loads(path.read_text(encoding="utf-8"))
    K = np.array([[meta["fl_x"], 0.0, meta["cx"]], [0.0, meta["fl_y"], meta["cy"]], [0.0, 0.0, 1.0]])
    val = set(meta.get("val_filenames", []))
    views = []
    for frame in meta["frames"]:
        c2w = nerfstudio_to_opencv_c2w(frame["transform_matrix"])
        views.append(DatasetView(Path(frame["file_path"]).name, c2w, np.linalg.inv(c2w), K, frame["file_path"] in val))
    return meta, views
