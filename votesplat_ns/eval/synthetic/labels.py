"""LERF-OVS label files for a scene with exact instance masks (our synthetic scenes)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
from PIL import Image

from votesplat_ns.eval.lerf_labels import frame_from_masks, write_label_frame


def write_scene_labels(scene_dir: Path, output_dir: Path, frames: Optional[Sequence[str]] = None) -> List[Path]:
    """LERF-OVS label files for a scene with ground-truth instance masks (our synthetic scenes).

    Reads ``transforms.json``: object names from ``instances`` (``{id, name}``; objects sharing a
    name form one category) and each frame's ``instance_mask_path`` (uint16 PNG, 0 = background).
    ``frames`` are image file names (default: the scene's evaluation frames, else every frame).
    Writes ``<image stem>.json`` per frame (objects not visible in a frame are not labelled) and
    returns the paths.
    """
    scene_dir = Path(scene_dir)
    transforms_path = scene_dir / "transforms.json" if scene_dir.is_dir() else scene_dir
    if not transforms_path.is_file():
        raise ValueError(f"{transforms_path} not found; pass a scene folder with transforms.json")
    scene_dir = transforms_path.parent
    meta = json.loads(transforms_path.read_text())
    objects = meta.get("instances")
    if not objects:
        raise ValueError(f"{transforms_path} lists no 'instances' with names; labels need the objects' names")
    names = {int(entry["id"]): str(entry["name"]) for entry in objects}
    by_name = {Path(frame["file_path"]).name: frame for frame in meta.get("frames", [])}
    if frames is None:
        frame_names: Sequence[str] = (
            (meta.get("votesplat_synthetic") or {}).get("eval_frames")
            or [Path(p).name for p in meta.get("test_filenames") or meta.get("val_filenames") or []]
            or sorted(by_name)
        )
    else:
        frame_names = frames
    written = []
    for frame_name in frame_names:
        frame = by_name.get(Path(frame_name).name)
        if frame is None:
            raise ValueError(
                f"frame {frame_name!r} is not in {transforms_path}; pass image file names such as {sorted(by_name)[:2]}"
            )
        if "instance_mask_path" not in frame:
            raise ValueError(
                f"frame {frame_name!r} of {transforms_path} has no instance_mask_path; labels need ground-truth masks"
            )
        label_image = np.asarray(Image.open(scene_dir / frame["instance_mask_path"])).astype(np.int64)
        masks: Dict[str, List[np.ndarray]] = {}
        for instance_id, name in names.items():
            mask = label_image == instance_id
            if mask.any():
                masks.setdefault(name, []).append(mask)
        if not masks:
            continue
        label = frame_from_masks(Path(frame["file_path"]).name, masks, note=f"from {frame['instance_mask_path']}")
        path = Path(output_dir) / f"{Path(frame['file_path']).stem}.json"
        write_label_frame(path, label)
        written.append(path)
    if not written:
        raise ValueError(f"no object is visible in the chosen frames of {transforms_path}; no labels written")
    return written
