"""Makes .gpu/fox: the fox capture at half resolution plus two levels of label masks, for the GPU runs.

Layout written (all read by nerfstudio's ``nerfstudio-data --downscale-factor 2`` and our
``--pipeline.datamanager.mask-source folder``):

    .gpu/fox/transforms.json                       copied as is (full-resolution intrinsics;
                                                   nerfstudio rescales cameras by 1/2 itself)
    .gpu/fox/images_2/<name>.jpg                   each image downscaled by 2, JPEG quality 90
    .gpu/fox/votesplat_masks/{coarse,fine}/<stem>.png
                                                   16-bit label PNGs (0 = no mask) at images_2 size

``images/`` is left out: with an explicit downscale factor nerfstudio 1.1.5 only opens
``images_<factor>/<name>`` (NerfstudioDataParser._get_fname), and it keeps the carried folder small.

The masks are NOT instance masks. The fox has no instance labels and no SAM weights exist
offline, so each level is a classical Felzenszwalb over-segmentation (scikit-image) at two
scales, with small segments merged into neighbours by ``min_size`` and the rest renumbered
1..K by decreasing area. They give the benchmark the same cost profile as real masks (a few
dozen to a few hundred labels per view, every pixel labelled), not the same quality: use them
to time votesplat against splatfacto, not to judge instance quality.

The folder is built beside the target and swapped in when complete, so an interrupted run never
leaves a half-made dataset behind.

Usage: .venv/bin/python scripts/gpu/prepare_fox.py [--src /work/shared/data/fox] [--dst .gpu/fox]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import shutil
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np
from PIL import Image

REPO_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_SRC = REPO_ROOT.parent / "shared" / "data" / "fox"
DEFAULT_DST = REPO_ROOT / ".gpu" / "fox"
MASK_FOLDER = "votesplat_masks"


@dataclass(frozen=True)
class SegmentationLevel:
    """One Felzenszwalb scale. ``min_size`` is in pixels of the downscaled image."""

    name: str
    scale: float
    sigma: float
    min_size: int


# At 540x960 these give tens of segments (coarse) and a few hundred (fine) per view, roughly
# the counts SAM's whole/part levels give on a tabletop scene.
LEVELS = (
    SegmentationLevel("coarse", scale=500.0, sigma=0.8, min_size=800),
    SegmentationLevel("fine", scale=150.0, sigma=0.8, min_size=150),
)


def downscale_image(image: Image.Image, factor: int) -> Image.Image:
    """Integer downscale with nerfstudio's rounding (int(size / factor)), area-correct filter."""
    width, height = image.size
    size = (width // factor, height // factor)
    return image.resize(size, resample=Image.Resampling.LANCZOS, reducing_gap=None)


def segment_labels(rgb: np.ndarray, level: SegmentationLevel) -> np.ndarray:
    """Felzenszwalb labels as uint16 [H, W], 1..K by decreasing segment area (0 is never used)."""
    from skimage.segmentation import felzenszwalb

    raw = felzenszwalb(rgb, scale=level.scale, sigma=level.sigma, min_size=level.min_size)
    ids, areas = np.unique(raw, return_counts=True)
    if len(ids) > np.iinfo(np.uint16).max:
        raise ValueError(f"{len(ids)} segments at level '{level.name}' do not fit a 16-bit PNG; raise min_size")
    # Stable order (area desc, then first-seen id) makes the output reproducible across runs.
    order = np.lexsort((ids, -areas))
    new_ids = np.empty(raw.max() + 1, dtype=np.uint16)
    new_ids[ids[order]] = np.arange(1, len(ids) + 1, dtype=np.uint16)
    return new_ids[raw]


def write_label_png(labels: np.ndarray, path: Path) -> None:
    if labels.dtype != np.uint16 or labels.ndim != 2:
        raise ValueError(f"label image for {path} must be uint16 [H, W], got {labels.dtype} {labels.shape}")
    Image.fromarray(labels).save(path, format="PNG", optimize=True)


def process_view(task: Tuple[Path, Path, str, int, int]) -> Dict[str, int]:
    """Downscale one image and segment it; returns the segment count per level."""
    source, dst_root, image_name, factor, quality = task
    with Image.open(source) as image:
        small = downscale_image(image.convert("RGB"), factor)
    small.save(dst_root / f"images_{factor}" / image_name, format="JPEG", quality=quality)
    rgb = np.asarray(small)
    counts = {}
    for level in LEVELS:
        labels = segment_labels(rgb, level)
        write_label_png(labels, dst_root / MASK_FOLDER / level.name / f"{Path(image_name).stem}.png")
        counts[level.name] = int(labels.max())
    return counts


def frame_image_names(transforms: dict, src: Path) -> List[str]:
    names = []
    for frame in transforms.get("frames", []):
        relative = Path(frame["file_path"])
        if not (src / relative).is_file():
            raise ValueError(f"{src / relative} (listed in transforms.json) does not exist; pass --src <fox folder>")
        names.append(relative.name)
    if not names:
        raise ValueError(f"{src / 'transforms.json'} lists no frames")
    if len(set(names)) != len(names):
        raise ValueError("transforms.json lists two frames with the same file name; images_N/ cannot hold both")
    return names


def folder_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def swap_in(staging: Path, dst: Path) -> None:
    """Replace ``dst`` by ``staging`` with two renames (each atomic on one filesystem)."""
    retired = dst.with_name(f"{dst.name}.old-{os.getpid()}")
    if dst.exists():
        os.replace(dst, retired)
    os.replace(staging, dst)
    shutil.rmtree(retired, ignore_errors=True)


def verify_with_nerfstudio(dst: Path, factor: int) -> int:
    """Run nerfstudio's own dataparser on the result; returns the number of train images."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    outputs = NerfstudioDataParserConfig(data=dst, downscale_factor=factor).setup().get_dataparser_outputs("train")
    missing = [p for p in outputs.image_filenames if not Path(p).is_file()]
    if missing:
        raise RuntimeError(
            f"nerfstudio's dataparser wants {missing[0]} (and {len(missing) - 1} more), which was not written"
        )
    with Image.open(outputs.image_filenames[0]) as first:
        width, height = first.size
    camera_size = (int(outputs.cameras.width[0]), int(outputs.cameras.height[0]))
    if camera_size != (width, height):
        raise RuntimeError(f"camera size {camera_size} != image size {(width, height)}")
    return len(outputs.image_filenames)


def main(argv: List[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--src", type=Path, default=DEFAULT_SRC, help="fox folder with transforms.json and images/")
    parser.add_argument("--dst", type=Path, default=DEFAULT_DST, help="output folder (replaced when complete)")
    parser.add_argument("--factor", type=int, default=2, help="downscale factor (nerfstudio's --downscale-factor)")
    parser.add_argument("--quality", type=int, default=90, help="JPEG quality of the downscaled images")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--no-verify", action="store_true", help="skip the check with nerfstudio's dataparser")
    args = parser.parse_args(argv)

    if args.factor < 2:
        parser.error("--factor must be >= 2 (factor 1 would need images/, which this script does not write)")
    if not 1 <= args.quality <= 100:
        parser.error("--quality must be within 1..100")
    transforms_path = args.src / "transforms.json"
    if not transforms_path.is_file():
        parser.error(f"{transforms_path} not found; pass --src <folder holding transforms.json>")
    transforms = json.loads(transforms_path.read_text())
    try:
        names = frame_image_names(transforms, args.src)
    except ValueError as error:
        parser.error(str(error))

    dst = args.dst.resolve()
    staging = dst.with_name(f"{dst.name}.tmp-{os.getpid()}")
    shutil.rmtree(staging, ignore_errors=True)
    (staging / f"images_{args.factor}").mkdir(parents=True)
    for level in LEVELS:
        (staging / MASK_FOLDER / level.name).mkdir(parents=True)
    try:
        shutil.copy2(transforms_path, staging / "transforms.json")
        license_file = args.src / "LICENSE.txt"
        if license_file.is_file():
            shutil.copy2(license_file, staging / "LICENSE.txt")
        tasks = [
            (args.src / Path(frame["file_path"]), staging, Path(frame["file_path"]).name, args.factor, args.quality)
            for frame in transforms["frames"]
        ]
        # spawn, not fork: after a forked pool the nerfstudio/torch import below hung once here.
        with ProcessPoolExecutor(
            max_workers=max(1, args.workers), mp_context=multiprocessing.get_context("spawn")
        ) as pool:
            counts = []
            for done, view_counts in enumerate(pool.map(process_view, tasks), start=1):
                counts.append(view_counts)
                if done % 10 == 0 or done == len(tasks):
                    print(f"segmented {done}/{len(tasks)} views", flush=True)
        swap_in(staging, dst)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise

    for level in LEVELS:
        per_view = np.array([c[level.name] for c in counts])
        print(f"{level.name}: {per_view.min()}..{per_view.max()} segments per view (mean {per_view.mean():.0f})")
    print(
        f"{len(names)} views; {dst} holds {folder_size(dst) / 1e6:.1f} MB "
        f"(images_{args.factor} {folder_size(dst / f'images_{args.factor}') / 1e6:.1f} MB, "
        f"masks {folder_size(dst / MASK_FOLDER) / 1e6:.1f} MB)"
    )
    if not args.no_verify:
        try:
            count = verify_with_nerfstudio(dst, args.factor)
        except ImportError:
            print("nerfstudio not importable here; skipped the dataparser check (run with .venv/bin/python)")
        else:
            print(f"nerfstudio's dataparser reads {count} train images from images_{args.factor}/ at the cameras' size")
    return 0


if __name__ == "__main__":
    sys.exit(main())
