"""The LERF-OVS 3D object-selection evaluation protocol (OpenGaussian's).

Protocol (OpenGaussian, ``scripts/compute_lerf_iou.py``): every (frame, category) pair of a scene is
one query; objects of one category in a frame are merged into one ground-truth mask; the predicted
mask comes from the selected Gaussians (e.g. their rendered accumulated opacity > 0.7); IoU with a
zero union counts 0, a missing prediction counts 0; a scene's mIoU is the mean IoU over its queries
and mAcc@0.25 the fraction of queries with IoU strictly above 0.25; the benchmark number is the
mean over scenes.

The label files (format, pixel convention, reading and writing) are :mod:`votesplat_ns.eval.lerf_labels`
and the mask checks :mod:`votesplat_ns.eval.lerf_masks`; their names are importable from here too.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np

from votesplat_ns.eval.lerf_labels import (
    LabelFrame as LabelFrame,
    LabelObject as LabelObject,
    LabelWarning as LabelWarning,
    Polygon as Polygon,
    category_masks as category_masks,
    frame_from_masks as frame_from_masks,
    frame_image_index as frame_image_index,
    label_frame_to_json as label_frame_to_json,
    load_label_frame as load_label_frame,
    load_scene_labels as load_scene_labels,
    mask_to_polygons as mask_to_polygons,
    parse_label_frame as parse_label_frame,
    polygon_area as polygon_area,
    polygon_bbox as polygon_bbox,
    polygon_perimeter as polygon_perimeter,
    rasterise_polygon as rasterise_polygon,
    write_label_frame as write_label_frame,
)
from votesplat_ns.eval.lerf_masks import (
    SILHOUETTE_THRESHOLD as SILHOUETTE_THRESHOLD,
    as_bool_mask,
    mask_iou as mask_iou,
    silhouette_mask as silhouette_mask,
)

ACCURACY_IOU_THRESHOLDS = (0.25, 0.5)


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
                iou = mask_iou(as_bool_mask(prediction, f"prediction for {frame.stem}/{category!r}"), ground_truth)
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
