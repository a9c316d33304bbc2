"""Seconds per image of SAM mask generation (the vote maps' preprocessing), on the device present.

    python benchmarks/bench_sam.py --image path/to/frame.png --model-types vit_b vit_h --width 1920 --height 1080

Runs the real ``SamMaskSource`` (segment_anything's unmodified ``SamAutomaticMaskGenerator``,
LangSplat's generator settings, levels s/m/l with one encoder pass per crop shared by the three
levels) with RANDOMLY INITIALISED weights: no checkpoint can be downloaded here. The image
encoder's cost does not depend on the weights, so the ``encoder`` column is what real weights
cost; the mask decoder and post-processing (``masks`` column) depend on how many masks survive
the quality filters, which random weights change, so read that column as indicative only.
Prints a markdown table; ``--json`` writes the numbers too (atomically).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


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


def bench(model_type: str, image: np.ndarray, repeats: int, device: str) -> dict:
    import torch
    from segment_anything import sam_model_registry

    from votesplat_ns.core.mask_sources import SamMaskSource

    torch.manual_seed(0)
    sam = sam_model_registry[model_type](checkpoint=None)
    source = SamMaskSource(
        model_type=model_type, device=device, sam_model=sam, levels=("s", "m", "l"), max_long_side=None
    )
    generator = source._build_generator()
    source._generator = generator
    predictor = generator.predictor
    # warm-up (cuDNN autotune, allocator), not timed
    predictor.set_image(np.ascontiguousarray(image[:512, :512]))
    predictor.clear_embeddings()
    synchronize()
    encoder, total, counts = [], [], []
    for _ in range(repeats):
        start = time.perf_counter()
        with torch.no_grad():
            predictor.set_image(image)
        synchronize()
        encoder.append(time.perf_counter() - start)
        predictor.clear_embeddings()
        start = time.perf_counter()
        labels = source.masks_for_image(image, "bench.png", 0)
        synchronize()
        total.append(time.perf_counter() - start)
        counts.append([int(np.unique(level).size - 1) for level in labels])
    peak = torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else float("nan")
    del source, generator, predictor, sam
    if torch.cuda.is_available():
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
    return {
        "model_type": model_type,
        "encoder_s": float(np.median(encoder)),
        "masks_s": float(np.median(total)),
        "masks_per_level": counts[-1],
        "peak_mib": round(peak, 1),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--image", type=Path, default=None, help="a photo to segment (default: a smooth random image)")
    parser.add_argument("--model-types", nargs="+", default=["vit_b", "vit_h"], choices=["vit_b", "vit_l", "vit_h"])
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1080)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--device", default=None, help="default: cuda if present, else cpu")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    import torch

    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    if args.image is not None and not args.image.is_file():
        parser.error(f"{args.image} is not a file; pass an image or leave --image out")
    image = load_image(args.image, args.width, args.height)
    gpu = torch.cuda.get_device_name() if device == "cuda" else "cpu"
    rows = [bench(model_type, image, args.repeats, device) for model_type in args.model_types]
    print(
        f"SAM mask generation, random weights, {args.width}x{args.height}, levels s/m/l, {gpu}, median of {args.repeats}"
    )
    print("| model | encoder (s, one pass) | masks, 3 levels (s/image) | masks per level | peak MiB |")
    print("|---|---|---|---|---|")
    for row in rows:
        print(
            f"| {row['model_type']} | {row['encoder_s']:.3f} | {row['masks_s']:.2f} | {row['masks_per_level']} | {row['peak_mib']:.0f} |"
        )
    if args.json is not None:
        from votesplat_ns.core.ply_io import atomic_write

        with atomic_write(args.json, "w") as handle:
            json.dump({"device": gpu, "width": args.width, "height": args.height, "rows": rows}, handle, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
