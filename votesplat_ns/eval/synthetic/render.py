"""Render a :mod:`~votesplat_ns.eval.synthetic.scenes` scene with mitsuba 3 and write a nerfstudio dataset.

* RGB: mitsuba's path tracer (``scalar_rgb`` variant, CPU), box pixel filter, sRGB 8-bit PNG (or JPEG
  with ``RenderSettings(image_format="jpg")``: 4:4:4 chroma, for datasets that must travel small).
* Instance ids, part ids and depth: ONE ray per pixel through the pixel centre (x + 0.5, y + 0.5)
  cast with ``scene.ray_intersect`` on the same mitsuba scene, so label edges are exact and agree with
  the depth. 16-bit single-channel PNGs; 0 = background/nothing.
* Depth: camera z (OpenCV, along the optical axis, not the ray length) in millimetres, uint16; 0 where
  no surface was hit or z > 65.535 m. nerfstudio reads it with its default ``depth_unit_scale_factor``
  of 1e-3.

Dataset layout (``transforms.json`` is written last, so a folder without it is an unfinished run)::

    transforms.json   nerfstudio format + "instances", "touching", "votesplat_synthetic"
    images/frame_00001.png (.jpg)  instances/frame_00001.png  parts/frame_00001.png  depth/frame_00001.png
    sparse_pc.ply     surface points seen by >= 2 training views, RGB albedo (SfM stand-in)

The file writers and readers (numpy and Pillow only, not mitsuba) are in
:mod:`votesplat_ns.eval.synthetic.dataset_files` and the point cloud in
:mod:`votesplat_ns.eval.synthetic.point_cloud`; their names are importable from here too.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np

from votesplat_ns.core.ply_io import jsonable
from votesplat_ns.eval.synthetic.dataset_files import (
    DEPTH_UNIT_METRES as DEPTH_UNIT_METRES,
    OPENCV_TO_OPENGL as OPENCV_TO_OPENGL,
    DatasetView as DatasetView,
    encode_depth_mm as encode_depth_mm,
    frame_name as frame_name,
    nerfstudio_to_opencv_c2w as nerfstudio_to_opencv_c2w,
    opencv_c2w_to_nerfstudio as opencv_c2w_to_nerfstudio,
    read_depth_png as read_depth_png,
    read_label_png as read_label_png,
    read_views as read_views,
    scene_from_dataset as scene_from_dataset,
    write_jpeg as write_jpeg,
    write_json as write_json,
    write_png as write_png,
    write_point_ply as write_point_ply,
)
from votesplat_ns.eval.synthetic.point_cloud import sparse_point_cloud as sparse_point_cloud
from votesplat_ns.eval.synthetic.scenes import (
    GENERATOR_VERSION,
    Camera,
    Part,
    Scene,
    linear_to_srgb_uint8,
    primitive_mesh,
    srgb_to_linear,
)

MITSUBA_MISSING = "mitsuba not installed (pip install votesplat_ns[synthetic])"
MITSUBA_VARIANT = "scalar_rgb"
# mitsuba's camera frame has +x to the image's left and +y up (it looks along +z)
_OPENCV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])
_SUBDIRS = ("images", "instances", "parts", "depth")


def require_mitsuba():
    """Import mitsuba and select the CPU ``scalar_rgb`` variant; clear error if it is missing."""
    try:
        import mitsuba as mi
    except ImportError as exc:
        raise ImportError(MITSUBA_MISSING) from exc
    if mi.variant() != MITSUBA_VARIANT:
        mi.set_variant(MITSUBA_VARIANT)
        mi.set_log_level(mi.LogLevel.Error)
    return mi


def mitsuba_available() -> bool:
    try:
        import mitsuba  # noqa: F401
    except ImportError:
        return False
    return True


def _write_mesh_ply(path: str, mesh) -> None:
    from plyfile import PlyData, PlyElement

    fields = [("x", "f4"), ("y", "f4"), ("z", "f4"), ("nx", "f4"), ("ny", "f4"), ("nz", "f4"), ("u", "f4"), ("v", "f4")]
    vertex = np.zeros(len(mesh.vertices), dtype=fields)
    vertex["x"], vertex["y"], vertex["z"] = mesh.vertices.astype(np.float32).T
    vertex["nx"], vertex["ny"], vertex["nz"] = mesh.normals.astype(np.float32).T
    vertex["u"], vertex["v"] = mesh.uvs.astype(np.float32).T
    faces = mesh.faces
    face = np.zeros(len(faces), dtype=[("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = faces
    PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(face, "face")], text=False).write(path)


# --------------------------------------------------------------------------------------------
# camera rays


def pixel_rays(camera: Camera, intrinsics) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World ray origin [3], unit directions [H,W,3] through pixel centres, and the camera z of each unit direction."""
    w, h = intrinsics.width, intrinsics.height
    xs = (np.arange(w) + 0.5 - intrinsics.cx) / intrinsics.fx
    ys = (np.arange(h) + 0.5 - intrinsics.cy) / intrinsics.fy
    dirs_cam = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], np.ones((1, 1))), axis=-1)
    norm = np.linalg.norm(dirs_cam, axis=-1, keepdims=True)
    dirs_cam = dirs_cam / norm
    dirs_world = dirs_cam @ camera.c2w[:3, :3].T
    return camera.c2w[:3, 3].copy(), dirs_world, dirs_cam[..., 2]


# --------------------------------------------------------------------------------------------
# mitsuba scene


class SceneRenderer:
    """A scene loaded into mitsuba: ``cast`` gives exact ids/depth, ``render_rgb`` path-traces colour."""

    def __init__(self, scene: Scene, max_depth: int = 4):
        mi = require_mitsuba()
        self.scene = scene
        self._mi = mi
        self.max_depth = int(max_depth)
        self.shape_labels: Dict[str, Tuple[int, int]] = {}
        entries: List[Tuple[int, Part]] = [(0, part) for part in scene.background] + scene.parts
        with tempfile.TemporaryDirectory(prefix="votesplat_synth_") as tmp:
            desc = {"type": "scene", "integrator": {"type": "path", "max_depth": self.max_depth}}
            n = 0
            for instance_id, part in entries:
                bsdf = self._bsdf(part)
                for primitive in part.primitives:
                    mesh = primitive_mesh(primitive)
                    key = f"shape_{n:04d}"
                    path = os.path.join(tmp, key + ".ply")
                    _write_mesh_ply(path, mesh)
                    desc[key] = {"type": "ply", "filename": path, "bsdf": bsdf}
                    self.shape_labels[key] = (instance_id, part.id)
                    n += 1
            light = scene.lighting
            desc["sun"] = {
                "type": "directional",
                "direction": list(light.sun_direction),
                "irradiance": {"type": "rgb", "value": light.sun_irradiance},
            }
            desc["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": light.ambient_radiance}}
            # optimize=False: merging shapes that share a material would lose their ids
            self.mi_scene = mi.load_dict(desc, optimize=False)

    def _bsdf(self, part: Part) -> dict:
        mi = self._mi
        if part.material.texture is not None:
            texture = self.scene.textures[part.material.texture]
            reflectance = {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(texture, dtype=np.float32))}
        else:
            linear = srgb_to_linear(np.asarray(part.material.srgb)).tolist()
            reflectance = {"type": "rgb", "value": linear}
        return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": reflectance}}

    def cast(self, camera: Camera) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(instance ids uint16 [H,W], part ids uint16 [H,W], camera-z depth float64 [H,W] metres, 0 = miss)."""
        mi = self._mi
        intr = self.scene.intrinsics
        origin, dirs, z_per_unit = pixel_rays(camera, intr)
        h, w = intr.height, intr.width
        instance = np.zeros((h, w), dtype=np.uint16)
        part = np.zeros((h, w), dtype=np.uint16)
        depth = np.zeros((h, w), dtype=np.float64)
        o = mi.Point3f(*origin.tolist())
        intersect = self.mi_scene.ray_intersect
        labels = self.shape_labels
        flat = dirs.reshape(-1, 3).tolist()
        for index, (dx, dy, dz) in enumerate(flat):
            si = intersect(mi.Ray3f(o, mi.Vector3f(dx, dy, dz)))
            if not si.is_valid():
                continue
            y, x = divmod(index, w)
            inst, prt = labels[si.shape.id()]
            instance[y, x] = inst
            part[y, x] = prt
            depth[y, x] = float(si.t) * z_per_unit[y, x]
        return instance, part, depth

    def sensor(self, camera: Camera, spp: int):
        mi = self._mi
        intr = self.scene.intrinsics
        if (
            abs(intr.cx - intr.width / 2.0) > 1e-9
            or abs(intr.cy - intr.height / 2.0) > 1e-9
            or abs(intr.fx - intr.fy) > 1e-9
        ):
            raise ValueError("the mitsuba sensor needs a centred principal point and square pixels (fx == fy)")
        to_world = np.asarray(camera.c2w, dtype=np.float64) @ _OPENCV_TO_MITSUBA
        return mi.load_dict(
            {
                "type": "perspective",
                "fov": intr.fov_x_degrees,
                "fov_axis": "x",
                "near_clip": 0.01,
                "far_clip": 1000.0,
                "to_world": mi.ScalarTransform4f(to_world.tolist()),
                "film": {
                    "type": "hdrfilm",
                    "width": intr.width,
                    "height": intr.height,
                    "rfilter": {"type": "box"},
                    "pixel_format": "rgb",
                },
                "sampler": {"type": "independent", "sample_count": int(spp)},
            }
        )

    def render_rgb(self, camera: Camera, spp: int = 64, seed: int = 0) -> np.ndarray:
        """Path-traced sRGB uint8 [H,W,3]."""
        mi = self._mi
        # mitsuba's stub types seed as a drjit UInt; render takes a Python int (its own default is 0)
        image = mi.render(
            self.mi_scene,
            sensor=self.sensor(camera, spp),
            spp=int(spp),
            seed=int(seed),  # pyright: ignore[reportArgumentType]
        )
        linear = np.array(image, dtype=np.float64)[..., :3]
        return linear_to_srgb_uint8(linear)


# --------------------------------------------------------------------------------------------
# dataset writer


IMAGE_FORMATS = ("png", "jpg")


@dataclass(frozen=True)
class RenderSettings:
    spp: int = 64
    max_depth: int = 4
    num_points: int = 4000
    image_format: str = "png"  # RGB images: "png" (lossless) or "jpg"; labels and depth are always PNG
    jpeg_quality: int = 95


def _prepare_output(output_dir: Path, overwrite: bool) -> None:
    if output_dir.exists() and not output_dir.is_dir():
        raise ValueError(f"{output_dir} exists and is not a folder; choose another output directory")
    ours = [output_dir / d for d in _SUBDIRS] + [output_dir / "transforms.json", output_dir / "sparse_pc.ply"]
    existing = [p for p in ours if p.exists()]
    if existing and not overwrite:
        raise ValueError(f"{output_dir} already holds a dataset ({existing[0].name}); pass --overwrite to replace it")
    for path in existing:
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()
    output_dir.mkdir(parents=True, exist_ok=True)


def write_dataset(
    scene: Scene,
    output_dir,
    settings: RenderSettings = RenderSettings(),
    overwrite: bool = False,
    progress: Optional[Callable[[int, int], None]] = None,
) -> Path:
    """Render every view of ``scene`` and write the dataset; returns the path of ``transforms.json``."""
    if settings.spp < 1:
        raise ValueError(f"spp must be at least 1 (got {settings.spp})")
    if settings.image_format not in IMAGE_FORMATS:
        raise ValueError(f"image format must be one of {', '.join(IMAGE_FORMATS)} (got {settings.image_format!r})")
    if not 1 <= settings.jpeg_quality <= 100:
        raise ValueError(f"JPEG quality must be between 1 and 100 (got {settings.jpeg_quality})")
    output_dir = Path(output_dir)
    mi = require_mitsuba()
    _prepare_output(output_dir, overwrite)
    renderer = SceneRenderer(scene, max_depth=settings.max_depth)
    intr = scene.intrinsics
    frames, depths = [], []
    eval_set = set(scene.eval_indices)
    for index, camera in enumerate(scene.cameras):
        name = frame_name(index)
        image_name = frame_name(index, settings.image_format)
        instance, part, depth = renderer.cast(camera)
        rgb = renderer.render_rgb(camera, spp=settings.spp, seed=scene.seed * 100_003 + index)
        if settings.image_format == "jpg":
            write_jpeg(output_dir / "images" / image_name, rgb, settings.jpeg_quality)
        else:
            write_png(output_dir / "images" / image_name, rgb)
        write_png(output_dir / "instances" / name, instance)
        write_png(output_dir / "parts" / name, part)
        depth_mm = encode_depth_mm(depth)
        write_png(output_dir / "depth" / name, depth_mm)
        depths.append(depth_mm.astype(np.float64) * DEPTH_UNIT_METRES)
        frames.append(
            {
                "file_path": f"images/{image_name}",
                "transform_matrix": opencv_c2w_to_nerfstudio(camera.c2w).tolist(),
                "instance_mask_path": f"instances/{name}",
                "part_mask_path": f"parts/{name}",
                "depth_file_path": f"depth/{name}",
            }
        )
        if progress is not None:
            progress(index + 1, len(scene.cameras))
    points, colours = sparse_point_cloud(scene, depths, settings.num_points)
    write_point_ply(output_dir / "sparse_pc.ply", points, colours)

    instances = []
    for obj in scene.objects:
        lo, hi = scene.object_bounds(obj)
        instances.append(
            {
                "id": obj.id,
                "name": obj.name,
                "kind": obj.kind,
                "colour": obj.colour,
                "parts": [{"id": p.id, "name": p.name} for p in obj.parts],
                "centre": ((lo + hi) / 2.0).tolist(),
                "interior_point": np.asarray(obj.interior_point).tolist(),
                "bbox_min": lo.tolist(),
                "bbox_max": hi.tolist(),
            }
        )
    meta = {
        "camera_model": "OPENCV",
        "fl_x": intr.fx,
        "fl_y": intr.fy,
        "cx": intr.cx,
        "cy": intr.cy,
        "w": intr.width,
        "h": intr.height,
        "k1": 0.0,
        "k2": 0.0,
        "k3": 0.0,
        "k4": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        "frames": frames,
        "ply_file_path": "sparse_pc.ply",
    }
    if eval_set:
        meta["train_filenames"] = [f["file_path"] for i, f in enumerate(frames) if i not in eval_set]
        meta["val_filenames"] = [f["file_path"] for i, f in enumerate(frames) if i in eval_set]
        # nerfstudio asks for the "test" split when loading for inference (viewer, ns-render)
        meta["test_filenames"] = list(meta["val_filenames"])
    meta["instances"] = instances
    meta["touching"] = [list(pair) for pair in scene.touching]
    meta["background_parts"] = [part.name for part in scene.background]
    meta["votesplat_synthetic"] = {
        "recipe": scene.recipe,
        "seed": scene.seed,
        "generator_version": GENERATOR_VERSION,
        "mitsuba_version": mi.__version__,
        "mitsuba_variant": MITSUBA_VARIANT,
        "spp": settings.spp,
        "max_depth": settings.max_depth,
        # PNG datasets keep the keys they always had
        **({"image_format": "jpg", "jpeg_quality": settings.jpeg_quality} if settings.image_format == "jpg" else {}),
        "num_views": len(scene.cameras) - len(eval_set),
        "num_eval_views": len(eval_set),
        "eval_frames": [frame_name(i, settings.image_format) for i in sorted(eval_set)],
        "width": intr.width,
        "height": intr.height,
        "scene_options": jsonable(scene.parameters.get("options", {})),
        "parameters": jsonable({k: v for k, v in scene.parameters.items() if k != "options"}),
        "world": "metres, z up; instance centres/boxes are in this frame (before nerfstudio's dataparser transform)",
        "depth_encoding": "uint16 PNG, millimetres of camera z (along the optical axis), 0 = no surface",
        "label_encoding": "uint16 PNG; instances 1..K, parts globally unique, 0 = background",
    }
    out = output_dir / "transforms.json"
    write_json(out, meta)
    return out
