"""LERF-OVS label files: reading, rasterising and writing them (the protocol is :mod:`votesplat_ns.eval.lerf_ovs`).

Label files are the per-frame JSONs LangSplat prepared for the LERF scenes (ISAT style):
``info{name, width, height, depth, note}`` and ``objects[]{category, group, segmentation
[[x, y], ...], area, layer, bbox [x1, y1, x2, y2], iscrowd, note}``. ``area`` is the shoelace area of
the polygon and ``bbox`` its vertex extremes.

Pixel convention of the polygons: exactly LangSplat's evaluation (``eval/utils.py``
``polygon_to_mask``): the vertices are cast with ``np.asarray(points, dtype=np.int32)`` (fractional
coordinates truncate toward zero) and filled with ``cv2.fillPoly(mask, [points], 1)`` (8-connected
edges, no sub-pixel shift), so a vertex (x, y) names pixel column trunc(x), row trunc(y) and the
outline pixels belong to the mask. OpenGaussian's ``compute_lerf_iou.py`` reads these masks after
LangSplat saved them as JPEG (0/255, read back with a threshold of 10); on the 22 published frames
that round trip changes no pixel, so the masks here are the ones both papers score against. In the
project's continuous frame the polygon runs through pixel centres (trunc(x) + 0.5, trunc(y) + 0.5),
so a mask has about area + perimeter/2 pixels (Pick's theorem gives area + boundary_points/2 + 1
lattice points on or inside an integer polygon; cv2 adds a few more where an 8-connected slanted
edge steps outside the exact polygon).

numpy + OpenCV (``cv2``, a nerfstudio dependency) for the label rasteriser and :func:`mask_to_polygons`.
"""

from __future__ import annotations

import json
import math
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from votesplat_ns.core.ply_io import atomic_write
from votesplat_ns.errors import VoteSplatInputError
from votesplat_ns.eval.lerf_masks import as_bool_mask

Polygon = Tuple[Tuple[float, float], ...]
_FRAME_NUMBER = re.compile(r"_(\d+)(?:\.[A-Za-z0-9]+)?$")


class LabelWarning(UserWarning):
    """A label entry that is skipped (e.g. a polygon with fewer than 3 vertices)."""


@dataclass(frozen=True)
class LabelObject:
    """One annotated object: a category and one polygon (label pixel coordinates, see module doc)."""

    category: str
    polygon: Polygon
    area: float
    bbox: Tuple[float, float, float, float]
    group: int = 0
    layer: float = 0.0
    iscrowd: bool = False
    note: str = ""

    @property
    def vertices(self) -> np.ndarray:
        return np.asarray(self.polygon, dtype=np.float64).reshape(-1, 2)


@dataclass(frozen=True)
class LabelFrame:
    """One annotated frame: image name and size and its objects (in file order)."""

    name: str
    width: int
    height: int
    objects: Tuple[LabelObject, ...]
    depth: int = 3
    note: str = ""
    source: str = field(default="", compare=False)

    @property
    def stem(self) -> str:
        return Path(self.name).stem

    @property
    def frame_number(self) -> int:
        """The number in ``frame_00041.jpg`` (41); LERF numbers its images from 1."""
        match = _FRAME_NUMBER.search(self.name)
        if match is None:
            raise ValueError(f"frame name {self.name!r} has no trailing number like 'frame_00041.jpg'")
        return int(match.group(1))

    @property
    def categories(self) -> Tuple[str, ...]:
        """Distinct categories in order of first appearance."""
        return tuple(dict.fromkeys(obj.category for obj in self.objects))


# --------------------------------------------------------------------------------------------------
# Geometry


def polygon_area(polygon: Union[Polygon, np.ndarray]) -> float:
    """Shoelace area of a closed polygon [V, 2] (the labels' ``area`` field)."""
    vertices = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    x, y = vertices[:, 0], vertices[:, 1]
    return float(0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def polygon_perimeter(polygon: Union[Polygon, np.ndarray]) -> float:
    vertices = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    edges = np.roll(vertices, -1, axis=0) - vertices
    return float(np.hypot(edges[:, 0], edges[:, 1]).sum())


def polygon_bbox(polygon: Union[Polygon, np.ndarray]) -> Tuple[float, float, float, float]:
    vertices = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    return (
        float(vertices[:, 0].min()),
        float(vertices[:, 1].min()),
        float(vertices[:, 0].max()),
        float(vertices[:, 1].max()),
    )


def rasterise_polygon(polygon: Union[Polygon, np.ndarray], width: int, height: int) -> np.ndarray:
    """Bool [height, width] mask of one label polygon, pixel for pixel as LangSplat draws it (module doc)."""
    import cv2

    vertices = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    if vertices.shape[0] == 0:
        raise ValueError("rasterise_polygon got a polygon with no vertices")
    if not np.isfinite(vertices).all():
        raise ValueError("rasterise_polygon got a polygon with non-finite vertices")
    if np.abs(vertices).max() >= 2**31:
        raise ValueError("rasterise_polygon got vertices outside the int32 range the reference casts them to")
    if width < 1 or height < 1:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    # astype(int32) truncates toward zero, as np.asarray(points, dtype=np.int32) does in LangSplat.
    points = vertices.astype(np.int32)
    canvas = np.zeros((int(height), int(width)), dtype=np.uint8)
    cv2.fillPoly(canvas, [points], (1,))
    return canvas.astype(bool)


def category_masks(frame: LabelFrame) -> Dict[str, np.ndarray]:
    """Ground-truth mask per category of ``frame``: the union of its objects' polygons.

    A category whose merged mask has no pixel inside the image is left out with a :class:`LabelWarning`.
    """
    masks: Dict[str, np.ndarray] = {}
    for obj in frame.objects:
        mask = rasterise_polygon(obj.polygon, frame.width, frame.height)
        masks[obj.category] = masks[obj.category] | mask if obj.category in masks else mask
    for category in [c for c, m in masks.items() if not m.any()]:
        warnings.warn(
            f"{frame.source or frame.name}: category {category!r} covers no pixel of the image; not scored",
            LabelWarning,
            stacklevel=2,
        )
        del masks[category]
    return masks


# --------------------------------------------------------------------------------------------------
# Parsing


def _number(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{what} must be a finite number, got {value!r}")
    return float(value)


def parse_label_frame(data: Mapping[str, Any], source: str = "<label dict>") -> LabelFrame:
    """A :class:`LabelFrame` from the decoded JSON of one label file.

    Objects whose polygon has fewer than 3 vertices are skipped with a :class:`LabelWarning` (they
    enclose nothing); any other malformed entry is a ValueError naming the file and object.
    """
    if not isinstance(data, Mapping) or "info" not in data or "objects" not in data:
        raise ValueError(f"{source}: not a LERF-OVS label (needs top-level 'info' and 'objects')")
    info = data["info"]
    if not isinstance(info, Mapping):
        raise ValueError(f"{source}: 'info' must be an object with name, width and height")
    for key in ("name", "width", "height"):
        if key not in info:
            raise ValueError(f"{source}: info has no {key!r}")
    name = info["name"]
    if not isinstance(name, str) or not name:
        raise ValueError(f"{source}: info.name must be the image file name, got {name!r}")
    width, height = info["width"], info["height"]
    for key, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value) or value < 1:
            raise ValueError(f"{source}: info.{key} must be a positive integer, got {value!r}")
    if not isinstance(data["objects"], list):
        raise ValueError(f"{source}: 'objects' must be a list")

    objects: List[LabelObject] = []
    for index, raw in enumerate(data["objects"]):
        where = f"{source}: object {index}"
        if not isinstance(raw, Mapping):
            raise ValueError(f"{where} is not an object")
        category = raw.get("category")
        if not isinstance(category, str) or not category.strip():
            raise ValueError(f"{where} has no category name (got {category!r})")
        where = f"{where} ({category!r})"
        segmentation = raw.get("segmentation")
        if not isinstance(segmentation, list):
            raise ValueError(f"{where}: segmentation must be a list of [x, y] points")
        points = []
        for point in segmentation:
            if not isinstance(point, (list, tuple)) or len(point) != 2:
                raise ValueError(f"{where}: segmentation point {point!r} is not an [x, y] pair")
            points.append((_number(point[0], f"{where} x"), _number(point[1], f"{where} y")))
        if len(points) < 3:
            warnings.warn(
                f"{where}: polygon has {len(points)} vertices (< 3), encloses nothing; skipped",
                LabelWarning,
                stacklevel=2,
            )
            continue
        polygon = tuple(points)
        area = _number(raw["area"], f"{where} area") if raw.get("area") is not None else polygon_area(polygon)
        bbox_raw = raw.get("bbox")
        if bbox_raw is None:
            bbox = polygon_bbox(polygon)
        else:
            if not isinstance(bbox_raw, (list, tuple)) or len(bbox_raw) != 4:
                raise ValueError(f"{where}: bbox must be [x1, y1, x2, y2], got {bbox_raw!r}")
            bbox = tuple(_number(v, f"{where} bbox") for v in bbox_raw)
        objects.append(
            LabelObject(
                category=category,
                polygon=polygon,
                area=area,
                bbox=bbox,  # type: ignore[arg-type]
                group=int(raw.get("group", 0) or 0),
                layer=float(raw.get("layer", 0.0) or 0.0),
                iscrowd=bool(raw.get("iscrowd", False)),
                note=str(raw.get("note", "") or ""),
            )
        )
    return LabelFrame(
        name=name,
        width=int(width),
        height=int(height),
        objects=tuple(objects),
        depth=int(info.get("depth", 3) or 3),
        note=str(info.get("note", "") or ""),
        source=source,
    )


def load_label_frame(path: Union[str, os.PathLike]) -> LabelFrame:
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"label file not found: {path}")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: not valid JSON ({error})") from None
    return parse_label_frame(data, source=str(path))


def load_scene_labels(scene_dir: Union[str, os.PathLike], flag: str = "label folder") -> List[LabelFrame]:
    """All ``frame_*.json`` labels of one scene folder, ordered by frame number (``flag`` names the folder in errors)."""
    scene_dir = Path(scene_dir)
    if not scene_dir.exists():
        raise VoteSplatInputError(f"{flag} {scene_dir}: folder not found; point at one scene's label folder")
    if not scene_dir.is_dir():
        raise VoteSplatInputError(
            f"{flag} {scene_dir} is a file, not a folder; point at the folder that holds one scene's frame_*.json files"
        )
    paths = sorted(scene_dir.glob("frame_*.json"))
    if not paths:
        raise VoteSplatInputError(
            f"{flag} {scene_dir}: no frame_*.json label files in this folder; point at one scene's label folder"
        )
    frames = [load_label_frame(path) for path in paths]
    return sorted(frames, key=lambda frame: frame.frame_number)


def frame_image_index(frame: LabelFrame, num_images: int) -> int:
    """0-based index of ``frame`` in the scene's sorted image list (frame_00041.jpg -> 40, as LangSplat).

    Raises ValueError when the scene has fewer images than the label refers to.
    """
    index = frame.frame_number - 1
    if not 0 <= index < num_images:
        raise ValueError(
            f"label {frame.name} refers to image index {index}, outside the scene's {num_images} images; "
            "check that the labels belong to this scene and that all of its images were loaded"
        )
    return index


# --------------------------------------------------------------------------------------------------
# Writing (for synthetic scenes scored with the same code)


def mask_to_polygons(mask: np.ndarray) -> List[Polygon]:
    """Polygons, one per 8-connected component, tracing its outer boundary pixels.

    Rasterising them with :func:`rasterise_polygon` gives back the component with its holes filled
    (the label format has no holes). A component of one or two pixels gets its points repeated to
    the 3 vertices a label polygon needs.
    """
    import cv2

    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"mask must be [H, W], got shape {mask.shape}")
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    polygons = []
    for contour in contours:
        points = [(float(x), float(y)) for x, y in contour.reshape(-1, 2)]
        while len(points) < 3:
            points.append(points[-1])
        polygons.append(tuple(points))
    return polygons


def frame_from_masks(
    name: str, masks: Mapping[str, Union[np.ndarray, Sequence[np.ndarray]]], note: str = ""
) -> LabelFrame:
    """A :class:`LabelFrame` from named ground-truth masks (e.g. a synthetic scene's objects).

    ``masks[category]`` is one [H, W] bool mask or a list of them (several objects of one
    category). Every connected component becomes one labelled object; an empty mask (object not
    visible in this frame) adds nothing, as LERF annotates only visible objects.
    """
    shape: Optional[Tuple[int, int]] = None
    objects: List[LabelObject] = []
    for category, value in masks.items():
        if not isinstance(category, str) or not category.strip():
            raise ValueError(f"category names must be non-empty strings, got {category!r}")
        instances = [value] if isinstance(value, np.ndarray) and value.ndim == 2 else list(value)
        for mask in instances:
            mask = as_bool_mask(mask, f"mask of {category!r}")
            if shape is None:
                shape = (mask.shape[0], mask.shape[1])
            elif mask.shape != shape:
                raise ValueError(
                    f"mask of {category!r} has shape {mask.shape}, others {shape}; all masks must share the image size"
                )
            for polygon in mask_to_polygons(mask):
                objects.append(
                    LabelObject(
                        category=category,
                        polygon=polygon,
                        area=polygon_area(polygon),
                        bbox=polygon_bbox(polygon),
                        group=len(objects) + 1,
                        layer=float(len(objects) + 1),
                    )
                )
    if shape is None:
        raise ValueError("frame_from_masks got no masks; pass {category: [H, W] bool mask}")
    return LabelFrame(name=name, width=shape[1], height=shape[0], objects=tuple(objects), note=note)


def label_frame_to_json(frame: LabelFrame) -> Dict[str, Any]:
    return {
        "info": {
            "name": frame.name,
            "width": frame.width,
            "height": frame.height,
            "depth": frame.depth,
            "note": frame.note,
        },
        "objects": [
            {
                "category": obj.category,
                "group": obj.group,
                "segmentation": [[x, y] for x, y in obj.polygon],
                "area": obj.area,
                "layer": obj.layer,
                "bbox": list(obj.bbox),
                "iscrowd": obj.iscrowd,
                "note": obj.note,
            }
            for obj in frame.objects
        ],
    }


def write_label_frame(path: Union[str, os.PathLike], frame: LabelFrame) -> None:
    """Write ``frame`` in the LERF-OVS label format, atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(label_frame_to_json(frame), indent=4, ensure_ascii=False)
    with atomic_write(path) as handle:
        handle.write(text.encode("utf-8"))
