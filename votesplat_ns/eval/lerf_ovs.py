"""LERF-OVS labels and the 3D object-selection evaluation protocol (OpenGaussian's).

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

Protocol (OpenGaussian, ``scripts/compute_lerf_iou.py``): every (frame, category) pair of a scene is
one query; objects of one category in a frame are merged into one ground-truth mask; the predicted
mask comes from the selected Gaussians (e.g. their rendered accumulated opacity > 0.7); IoU with a
zero union counts 0, a missing prediction counts 0; a scene's mIoU is the mean IoU over its queries
and mAcc@0.25 the fraction of queries with IoU strictly above 0.25; the benchmark number is the
mean over scenes.

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
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from votesplat_ns.core.ply_io import atomic_write

try:  # torch is optional here: predictions may be numpy arrays or tensors.
    import torch
except ImportError:  # pragma: no cover - torch is a project dependency
    torch = None

Polygon = Tuple[Tuple[float, float], ...]
# OpenGaussian thresholds the rendered silhouette (accumulated opacity) of the selected Gaussians at 0.7.
SILHOUETTE_THRESHOLD = 0.7
ACCURACY_IOU_THRESHOLDS = (0.25, 0.5)
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
    cv2.fillPoly(canvas, [points], 1)
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


def load_scene_labels(scene_dir: Union[str, os.PathLike]) -> List[LabelFrame]:
    """All ``frame_*.json`` labels of one scene folder, ordered by frame number."""
    scene_dir = Path(scene_dir)
    paths = sorted(scene_dir.glob("frame_*.json")) if scene_dir.is_dir() else []
    if not paths:
        raise ValueError(f"no frame_*.json label files in {scene_dir}; point at one scene's label folder")
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
            mask = _as_bool_mask(mask, f"mask of {category!r}")
            if shape is None:
                shape = mask.shape
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


# --------------------------------------------------------------------------------------------------
# Metrics


def _to_numpy(array: Any) -> np.ndarray:
    if torch is not None and isinstance(array, torch.Tensor):
        return array.detach().cpu().numpy()
    return np.asarray(array)


def _as_bool_mask(mask: Any, what: str) -> np.ndarray:
    mask = _to_numpy(mask)
    if mask.ndim != 2:
        raise ValueError(f"{what} must be [H, W], got shape {mask.shape}")
    if mask.dtype == bool:
        return mask
    if np.issubdtype(mask.dtype, np.integer) and np.isin(mask, (0, 1)).all():
        return mask.astype(bool)
    raise ValueError(
        f"{what} has dtype {mask.dtype}; pass a bool (or 0/1) mask, e.g. threshold the rendered "
        f"accumulated opacity with silhouette_mask(acc, {SILHOUETTE_THRESHOLD})"
    )


def silhouette_mask(accumulation: Any, threshold: float = SILHOUETTE_THRESHOLD) -> np.ndarray:
    """Bool mask from the accumulated opacity [H, W] (or [H, W, 1]) rendered for the selected Gaussians."""
    accumulation = _to_numpy(accumulation).astype(np.float64)
    if accumulation.ndim == 3 and accumulation.shape[-1] == 1:
        accumulation = accumulation[..., 0]
    if accumulation.ndim != 2:
        raise ValueError(f"accumulation must be [H, W] or [H, W, 1], got shape {accumulation.shape}")
    if not np.isfinite(accumulation).all():
        raise ValueError("accumulation has non-finite values; check the render")
    return accumulation > threshold


def mask_iou(predicted: Any, ground_truth: Any) -> float:
    """IoU of two bool masks of equal shape; 0 when both are empty (OpenGaussian's rule)."""
    predicted = _as_bool_mask(predicted, "predicted mask")
    ground_truth = _as_bool_mask(ground_truth, "ground-truth mask")
    if predicted.shape != ground_truth.shape:
        raise ValueError(
            f"predicted mask is {predicted.shape[1]}x{predicted.shape[0]} but the label is "
            f"{ground_truth.shape[1]}x{ground_truth.shape[0]}; render at the label resolution (scale the intrinsics)"
        )
    union = np.logical_or(predicted, ground_truth).sum()
    if union == 0:
        return 0.0
    return float(np.logical_and(predicted, ground_truth).sum() / union)


@dataclass(frozen=True)
class QueryScore:
    frame: str
    category: str
    iou: float


@dataclass(frozen=True)
class SceneScore:
    """Per-query IoUs of one scene and their summaries."""

    scene: str
    queries: Tuple[QueryScore, ...]

    @property
    def miou(self) -> float:
        return float(np.mean([query.iou for query in self.queries]))

    def accuracy(self, iou_threshold: float = 0.25) -> float:
        """Fraction of queries with IoU strictly above ``iou_threshold`` (mAcc@threshold)."""
        return float(np.mean([query.iou > iou_threshold for query in self.queries]))

    def to_dict(self) -> Dict[str, Any]:
        summary: Dict[str, Any] = {"scene": self.scene, "num_queries": len(self.queries), "mIoU": self.miou}
        for threshold in ACCURACY_IOU_THRESHOLDS:
            summary[f"mAcc@{threshold}"] = self.accuracy(threshold)
        summary["queries"] = [{"frame": q.frame, "category": q.category, "iou": q.iou} for q in self.queries]
        return summary


def evaluate_scene(
    frames: Sequence[LabelFrame],
    predict: Callable[[LabelFrame, str], Any],
    queries: Optional[Mapping[str, str]] = None,
    scene: str = "",
) -> SceneScore:
    """Score a 3D selection method on one scene's labelled frames.

    For every frame and every category in it, ``predict(frame, text)`` returns the predicted
    [height, width] bool mask at the label's resolution (or None for "nothing selected", scored 0).
    ``text`` is the category, or ``queries[category]`` where a category should be asked for with
    other words; a key of ``queries`` that is no category of these frames is a ValueError.
    """
    if len(frames) == 0:
        raise ValueError("evaluate_scene got no label frames; load them with load_scene_labels(scene_dir)")
    known = {category for frame in frames for category in frame.categories}
    queries = dict(queries or {})
    unknown = sorted(set(queries) - known)
    if unknown:
        raise ValueError(
            f"queries name categories {unknown} that are not in the labels; known categories: {sorted(known)}"
        )
    scores: List[QueryScore] = []
    for frame in frames:
        for category, ground_truth in category_masks(frame).items():
            prediction = predict(frame, queries.get(category, category))
            if prediction is None:
                iou = 0.0
            else:
                iou = mask_iou(_as_bool_mask(prediction, f"prediction for {frame.stem}/{category!r}"), ground_truth)
            scores.append(QueryScore(frame=frame.stem, category=category, iou=iou))
    if not scores:
        raise ValueError("the label frames contain no scorable category; check the label files")
    return SceneScore(scene=scene, queries=tuple(scores))


def summarise_scenes(scores: Sequence[SceneScore]) -> Dict[str, Any]:
    """Per-scene mIoU/mAcc and their mean over scenes (the number LERF-OVS tables report)."""
    if len(scores) == 0:
        raise ValueError("summarise_scenes got no scene scores")
    names = [score.scene for score in scores]
    if len(set(names)) != len(names):
        raise ValueError(f"scene names must be distinct to be summarised, got {names}")
    per_scene = {
        score.scene: {key: value for key, value in score.to_dict().items() if key != "queries"} for score in scores
    }
    metric_keys = ["mIoU"] + [f"mAcc@{threshold}" for threshold in ACCURACY_IOU_THRESHOLDS]
    mean = {key: float(np.mean([per_scene[name][key] for name in names])) for key in metric_keys}
    return {"scenes": per_scene, "mean": mean}
