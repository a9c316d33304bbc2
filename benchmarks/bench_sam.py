"""Seconds per image of SAM mask generation (the vote maps' preprocessing): per level and in one pass.

    python benchmarks/bench_sam.py --image path/to/frame.png --model-types vit_h --width 1920 --height 1080

No checkpoint can be downloaded here, so the weights are RANDOMLY INITIALISED. Two workloads, each
timed for both paths in the same call, with LangSplat's generator settings (32 x 32 points, one
crop layer: 5 crops, pred_iou 0.7, stability 0.85, min region 100) and levels s/m/l:
  - ``random``: the model's own outputs on ``--image``. Encoder and decoder cost what real weights
    cost, but few or no masks survive the filters, so the NMS / small-region / painting work of
    real weights is missing;
  - ``stand-in``: the model's encoder and decoder still run (their outputs dropped), and the
    decoder's outputs come from label maps at three granularities (tests/sam_stand_in.py), with
    which hundreds of masks survive per image, as with real weights; ``--images`` scenes.
Paths: ``per level`` is segment_anything's unmodified SamAutomaticMaskGenerator run once per level, the
encoder shared between the runs (tests/sam_reference.py); ``one pass`` is SamLevelsMaskGenerator, what
``votesplat masks`` and the training cache use. Both paths' label images are compared (pixels that
differ). ``one pass`` is also run once with its per-stage split (synchronised at each stage, so the
split's total is a little above the plain time; its ``decoder`` stage includes the stand-in's own
work). Peak GPU memory includes the stand-in's per-segment maps (up to a few GB at 1080p) in the
stand-in workload. Prints markdown tables; ``--json`` writes the numbers.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any, Dict

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # the oracle and the stand-in decoder are test code

LANGSPLAT: Dict[str, Any] = dict(
    points_per_side=32,
    points_per_batch=64,
    pred_iou_thresh=0.7,
    stability_score_thresh=0.85,
    box_nms_thresh=0.7,
    crop_n_layers=1,
    crop_n_points_downscale_factor=1,
    min_mask_region_area=100,
)


def load_image(path: Path | None, width: int, height: int) -> np.ndarray:
    from PIL import Image

    if path is None:  # smooth random colours: something for the generator to cut
        rng = np.random.default_rng(0)
        small = rng.integers(0, 256, size=(height // 60 + 1, width // 60 + 1, 3), dtype=np.uint8)
        return np.asarray(Image.fromarray(small).resize((width, height), Image.Resampling.BICUBIC))
    return np.asarray(Image.open(path).convert("RGB").resize((width, height), Image.Resampling.BICUBIC))


def synchronize() -> None:
    import torch

    if torch.cuda.is_available():
        torch.cuda.synchronize()


def reset_peak() -> None:
    import torch

    if torch.cuda.is_available():
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()


def peak_mib() -> float:
    import torch

    return torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else float("nan")


def timed(run):
    synchronize()
    start = time.perf_counter()
    result = run()
    synchronize()
    return result, time.perf_counter() - start


def bench_workload(sam, workload: str, images, levels, repeats: int, run_per_level: bool) -> dict:
    """``images``: (image, label maps or None) pairs; label maps select the stand-in decoder."""
    from sam_reference import ReferenceGenerator  # pyright: ignore[reportMissingImports]
    from sam_stand_in import StandInPredictor  # pyright: ignore[reportMissingImports]
    from segment_anything import SamPredictor

    from votesplat_ns.core.sam_masks import SamLevelsMaskGenerator

    def predictor(image, maps, seed):
        model = SamPredictor(sam)
        if maps is None:
            return model
        return StandInPredictor(
            image, maps, LANGSPLAT["crop_n_layers"], device=str(model.device), seed=seed, model_predictor=model
        )

    per_level_times, one_pass_times, per_level_peaks, one_pass_peaks = [], [], [], []
    differing, counts, pixels = [], [], 0
    stages: dict = {}
    for seed, (image, maps) in enumerate(images):
        one_pass = SamLevelsMaskGenerator(predictor(image, maps, seed), levels, **LANGSPLAT)
        one_pass.label_images(image)  # warm-up (cuDNN autotune, allocator, the stand-in's per-segment cache)
        for _ in range(repeats):
            reset_peak()
            labels, seconds = timed(lambda: one_pass.label_images(image))
            one_pass_times.append(seconds)
            one_pass_peaks.append(peak_mib())
        one_pass.stage_seconds = {}
        one_pass.label_images(image)
        for name, seconds in one_pass.stage_seconds.items():
            stages.setdefault(name, []).append(seconds)
        counts.append([int(np.unique(level).size - 1) for level in labels])
        if run_per_level:
            per_level = ReferenceGenerator(sam, predictor(image, maps, seed), levels, **LANGSPLAT)
            for _ in range(min(repeats, 1 if maps is not None else repeats)):
                reset_peak()
                expected, seconds = timed(lambda: per_level.label_images(image))
                per_level_times.append(seconds)
                per_level_peaks.append(peak_mib())
            differing.append(int(sum((a != b).sum() for a, b in zip(expected, labels))))
            pixels += sum(a.size for a in expected)
    return {
        "workload": workload,
        "images": len(images),
        "per_level_s": float(np.median(per_level_times)) if per_level_times else None,
        "one_pass_s": float(np.median(one_pass_times)),
        "one_pass_stages_s": {name: float(np.median(values)) for name, values in stages.items()},
        "masks_per_level": counts[-1],
        "masks_per_level_mean": [float(np.mean(column)) for column in zip(*counts)],
        "differing_pixels": int(sum(differing)) if run_per_level else None,
        "differing_images": int(sum(d > 0 for d in differing)) if run_per_level else None,
        "compared_pixels": pixels,
        "per_level_peak_mib": round(max(per_level_peaks), 1) if per_level_peaks else None,
        "one_pass_peak_mib": round(max(one_pass_peaks), 1),
    }


def encoder_seconds(sam, image: np.ndarray) -> float:
    """One encoder pass on the whole image, after a warm-up pass."""
    from segment_anything import SamPredictor

    encoder = SamPredictor(sam)
    encoder.set_image(image)
    return timed(lambda: encoder.set_image(image))[1]


def bench(model_type: str, image: np.ndarray, args) -> list:
    import torch
    from sam_stand_in import scene  # pyright: ignore[reportMissingImports]
    from segment_anything import sam_model_registry

    torch.manual_seed(0)
    sam = sam_model_registry[model_type](checkpoint=None).to(args.device).eval()
    rows = []
    levels = tuple(args.levels)
    for workload in args.workloads:
        if workload == "random":
            images = [(image, None)]
        else:
            images = [scene(args.height, args.width, seed=seed, fine_cells=args.cells) for seed in range(args.images)]
        row = bench_workload(sam, workload, images, levels, args.repeats, not args.one_pass_only)
        row.update(model_type=model_type, encoder_one_pass_s=encoder_seconds(sam, images[0][0]))
        rows.append(row)
        print(json.dumps(row), flush=True)
    del sam
    reset_peak()
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("--image", type=Path, default=None, help="a photo to segment (default: a smooth random image)")
    parser.add_argument("--model-types", nargs="+", default=["vit_h"], choices=["vit_b", "vit_l", "vit_h"])
    parser.add_argument("--workloads", nargs="+", default=["stand-in", "random"], choices=["stand-in", "random"])
    parser.add_argument("--levels", nargs="+", default=["s", "m", "l"], choices=["default", "s", "m", "l"])
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1080)
    parser.add_argument("--images", type=int, default=3, help="stand-in scenes (each compared with the per_level path)")
    parser.add_argument("--cells", type=int, default=300, help="finest segments per stand-in scene")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--one-pass-only", action="store_true", help="skip the per-level path (no comparison)")
    parser.add_argument("--device", default=None, help="default: cuda if present, else cpu")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    import torch

    args.device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    if args.image is not None and not args.image.is_file():
        parser.error(f"{args.image} is not a file; pass an image or leave --image out")
    image = load_image(args.image, args.width, args.height)
    gpu = torch.cuda.get_device_name() if args.device == "cuda" else "cpu"
    rows = [row for model_type in args.model_types for row in bench(model_type, image, args)]
    print(
        f"\nSAM masks, random weights, {args.width}x{args.height}, levels {'/'.join(args.levels)}, LangSplat's settings, "
        f"{gpu}; one pass: median of {args.repeats} after a warm-up; per level: one run per stand-in image"
    )
    print(
        "| model | workload | images | per level (s/image) | one pass (s/image) | masks per level | differing pixels | peak MiB per level / one pass |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        per_level = f"{row['per_level_s']:.2f}" if row["per_level_s"] is not None else "-"
        differ = "-" if row["differing_pixels"] is None else f"{row['differing_pixels']} of {row['compared_pixels']}"
        print(
            f"| {row['model_type']} | {row['workload']} | {row['images']} | {per_level} | {row['one_pass_s']:.3f} | "
            f"{row['masks_per_level']} | {differ} | {row['per_level_peak_mib']} / {row['one_pass_peak_mib']} |"
        )
    print("\none pass per stage (s/image; the stages' encoder is every crop's pass)")
    names = sorted({name for row in rows for name in row["one_pass_stages_s"]})
    print("| model | workload | one encoder pass, whole image | " + " | ".join(names) + " |")
    print("|---|---|---|" + "---|" * len(names))
    for row in rows:
        split = " | ".join(f"{row['one_pass_stages_s'].get(name, 0.0):.3f}" for name in names)
        print(f"| {row['model_type']} | {row['workload']} | {row['encoder_one_pass_s']:.3f} | {split} |")
    if args.json is not None:
        from votesplat_ns.core.ply_io import atomic_write

        with atomic_write(args.json, "w") as handle:
            json.dump({"device": gpu, "width": args.width, "height": args.height, "rows": rows}, handle, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
