"""Seconds per image of SAM mask generation (the vote maps' preprocessing): per level and in one pass.

    python benchmarks/bench_sam.py --image path/to/frame.png --model-types vit_h --width 1920 --height 1080
    python benchmarks/bench_sam.py --workloads stand-in --4k                 # 3840 x 2160, one pass: time and memory
    python benchmarks/bench_sam.py --workloads stand-in --no-model --images 10 --first-seed 10 --repeats 1
                                                                             # labels against the oracle only
    python benchmarks/bench_sam.py --precision fp32 tf32 bf16                 # faster precisions, agreement with fp32
    python benchmarks/bench_sam.py --workloads stand-in --one-pass-only --stream --processes 2
                                                                             # two interpreters on one GPU at once

No checkpoint can be downloaded here, so the weights are RANDOMLY INITIALISED. Two workloads, each
timed for both paths in the same call, with LangSplat's generator settings (32 x 32 points, one
crop layer: 5 crops, pred_iou 0.7, stability 0.85, min region 100; ``--points-per-side`` and the
thresholds can be changed) and levels s/m/l:
  - ``random``: the model's own outputs on ``--image``. Encoder and decoder cost what real weights
    cost, but few or no masks survive the filters, so the NMS / small-region / painting work of
    real weights is missing;
  - ``stand-in``: the model's encoder, decoder and upscaling still run (their outputs dropped), and
    the masks come from label maps at three granularities (tests/sam_stand_in.py), with which
    hundreds of masks survive per image, as with real weights; ``--images`` scenes (seeds from
    ``--first-seed``, so that a long identity check can be split over calls). ``--no-model``: the
    stand-in alone, no SAM model built, for the identity check only (its times are not SAM's).
Paths: ``per level`` is segment_anything's unmodified SamAutomaticMaskGenerator run once per level, the
encoder shared between the runs (tests/sam_reference.py), configured the same (``--points-per-batch``
included, so that its decoder calls are the one pass's); ``one pass`` is SamLevelsMaskGenerator, what
``votesplat masks`` and the training cache use, at each ``--precision``. The fp32 one pass's label
images are compared with the per-level path's (pixels that differ); another precision's with fp32's
as matched-mask IoU (each fp32 label region's best IoU with a region of the other precision's labels), and
the model's own masks prompt by prompt, before any filter (``--no-decoder-agreement`` skips it): with random
weights few masks pass the filters, and the stand-in's masks do not depend on the precision at all (its
labels agree by construction), so that comparison is the one that measures a precision.
``one pass`` is also run once with its per-stage split (synchronised at each stage, so the split's total
is a little above the plain time): encoder (every crop), decoder (prompt encoder + mask decoder),
filtering (upscaling, stability, boxes, NMS within and across crops), labels (the kept masks upscaled
again and copied to the host, small-region removal, painting). With the stand-in the decoder, filtering and
labels stages include the stand-in's own work on top of SAM's (finding each prompt's segments, copying a mask's
precomputed logits); ``stand_in_own`` is that part, synchronised (subtract it for SAM's own time). Peak GPU memory: the most allocated during a call,
and that minus what was allocated before it (the call's own memory: the stand-in's per-segment maps, a few
GB at 1080p and four times that at 4K, and the model's weights are held before). Prints markdown tables;
``--json`` writes the numbers (after each workload, so a call cut short keeps what it finished).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # the oracle and the stand-in decoder are test code

from votesplat_ns.core.sam_decoder import DECODER_MODES, DEFAULT_DECODER  # noqa: E402

LANGSPLAT: Dict[str, Any] = dict(
    points_per_side=32,
    pred_iou_thresh=0.7,
    stability_score_thresh=0.85,
    box_nms_thresh=0.7,
    crop_n_layers=1,
    crop_n_points_downscale_factor=1,
    min_mask_region_area=100,
)
STAGE_GROUPS = {
    "encoder": ("encoder",),
    "decoder": ("decoder",),
    "filtering": ("filter", "nms"),
    "labels": ("masks", "small_regions", "paint"),
}


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


def reset_peak() -> float:
    """Clears the peak; returns MiB allocated now."""
    import torch

    if not torch.cuda.is_available():
        return float("nan")
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats()
    return torch.cuda.memory_allocated() / 2**20


def peak_mib() -> float:
    import torch

    return torch.cuda.max_memory_allocated() / 2**20 if torch.cuda.is_available() else float("nan")


def timed(run, *args):
    synchronize()
    start = time.perf_counter()
    result = run(*args)
    synchronize()
    return result, time.perf_counter() - start


def matched_ious(reference: np.ndarray, other: np.ndarray) -> np.ndarray:
    """Each region of the label image ``reference`` (ids > 0): its best IoU with a region of ``other``."""
    a, b = reference.ravel().astype(np.int64), other.ravel().astype(np.int64)
    area_a, area_b = np.bincount(a), np.bincount(b)
    both = (a > 0) & (b > 0)
    base = int(b.max()) + 1
    pairs, overlap = np.unique(a[both] * base + b[both], return_counts=True)
    ia, ib = pairs // base, pairs % base
    best = np.zeros(len(area_a))
    np.maximum.at(best, ia, overlap / (area_a[ia] + area_b[ib] - overlap))
    return best[np.flatnonzero(area_a[1:]) + 1]


def agreement(reference: List[List[np.ndarray]], other: List[List[np.ndarray]]) -> dict:
    """Matched-mask IoU of ``other``'s label images against ``reference``'s (per image, per level)."""
    forward = np.concatenate([matched_ious(r, o) for rs, os in zip(reference, other) for r, o in zip(rs, os)])
    backward = np.concatenate([matched_ious(o, r) for rs, os in zip(reference, other) for r, o in zip(rs, os)])
    return {
        "regions_reference": int(forward.size),
        "regions_other": int(backward.size),
        "matched_iou_mean": float(forward.mean()) if forward.size else None,
        "matched_iou_median": float(np.median(forward)) if forward.size else None,
        "share_iou_ge_0_9": float(np.mean(forward >= 0.9)) if forward.size else None,
        "share_iou_ge_0_5": float(np.mean(forward >= 0.5)) if forward.size else None,
        "matched_iou_mean_other_to_reference": float(backward.mean()) if backward.size else None,
        "differing_pixels": int(sum((r != o).sum() for rs, os in zip(reference, other) for r, o in zip(rs, os))),
    }


def bench_workload(sam, workload: str, images, levels, args, settings) -> dict:
    """``images``: (seed, image, label maps or None) triples; label maps select the stand-in decoder."""
    from sam_reference import ReferenceGenerator  # pyright: ignore[reportMissingImports]
    from sam_stand_in import StandInPredictor  # pyright: ignore[reportMissingImports]
    from segment_anything import SamPredictor

    from votesplat_ns.core.sam_masks import SamLevelsMaskGenerator

    def predictor(image, maps, seed, precision):
        model = SamPredictor(sam) if sam is not None else None
        if maps is None:
            return model
        stand_in = StandInPredictor(
            image,
            maps,
            settings["crop_n_layers"],
            device=args.device,
            seed=seed,
            model_predictor=model,
            precision=precision,
            crops_per_encoder_pass=args.crops_per_encoder_pass,
            decoder=args.decoder,
            compile_decoder=args.compile_decoder,
        )
        stand_in.segment_maps()  # the stand-in's per-segment maps, made before any timing
        return stand_in

    def one_pass(image, maps, seed, precision):
        return SamLevelsMaskGenerator(
            predictor(image, maps, seed, precision),
            levels,
            **settings,
            precision=precision,
            crops_per_encoder_pass=args.crops_per_encoder_pass,
            decoder=args.decoder,
            compile_decoder=args.compile_decoder,
        )

    precisions = list(args.precision)
    one_pass_times: Dict[str, list] = {p: [] for p in precisions}
    peaks: Dict[str, list] = {p: [] for p in precisions}
    working: Dict[str, list] = {p: [] for p in precisions}
    stages: Dict[str, Dict[str, list]] = {p: {} for p in precisions}
    labels_of: Dict[str, list] = {p: [] for p in precisions}
    counts: Dict[str, list] = {p: [] for p in precisions}
    per_level_times, per_level_peaks, differing, pixels = [], [], [], 0
    for number, (seed, image, maps) in enumerate(images):
        for precision in precisions:
            generator = one_pass(image, maps, seed, precision)
            if number == 0 and args.device != "cpu":
                generator.label_images(image)  # warm-up (cuDNN autotune, allocator)
            labels = None
            for _ in range(max(1, args.repeats)):
                before = reset_peak()
                labels, seconds = timed(generator.label_images, image)
                one_pass_times[precision].append(seconds)
                peaks[precision].append(peak_mib())
                working[precision].append(peak_mib() - before)
            if args.repeats > 0:
                split: Dict[str, float] = {}
                generator.stage_seconds = split
                stand_in: Any = generator.steps if maps is not None else None
                if stand_in is not None:
                    stand_in.own_seconds = 0.0
                generator.label_images(image)
                for name, seconds in split.items():
                    stages[precision].setdefault(name, []).append(seconds)
                if stand_in is not None:
                    stages[precision].setdefault("stand_in_own", []).append(stand_in.own_seconds)
            assert labels is not None
            labels_of[precision].append(labels)
            counts[precision].append([int(np.unique(level).size - 1) for level in labels])
            del generator
        if not args.one_pass_only:
            # without a model, segment_anything's generator only reads the encoder's input size from it
            model = sam if sam is not None else SimpleNamespace(image_encoder=SimpleNamespace(img_size=1024))
            reference = ReferenceGenerator(model, predictor(image, maps, seed, "fp32"), levels, **settings)
            for _ in range(1 if maps is not None else max(1, args.repeats)):
                reset_peak()
                expected, seconds = timed(reference.label_images, image)
                per_level_times.append(seconds)
                per_level_peaks.append(peak_mib())
            if "fp32" in labels_of:
                fast = labels_of["fp32"][-1]
                differing.append(int(sum((a != b).sum() for a, b in zip(expected, fast))))
                pixels += sum(a.size for a in expected)
                print(f"  image {seed}: {differing[-1]} of {sum(a.size for a in expected)} pixels differ", flush=True)
            del reference
    streams = (
        {p: stream_seconds(images, one_pass, p, labels_of[p], args.together) for p in precisions} if args.stream else {}
    )
    rows = []
    for precision in precisions:
        split = {name: float(np.median(values)) for name, values in stages[precision].items()}
        row = {
            "workload": workload,
            "precision": precision,
            "decoder": args.decoder,
            "decoder_compiled": args.compile_decoder and args.device.startswith("cuda"),
            "images": len(images),
            "seeds": [seed for seed, _, _ in images],
            "model": "none (stand-in alone)" if sam is None else "SAM, random weights",
            "per_level_s": float(np.median(per_level_times)) if per_level_times else None,
            "one_pass_s": float(np.median(one_pass_times[precision])),
            "one_pass_stages_s": split,
            "one_pass_stage_groups_s": {
                group: sum(split.get(name, 0.0) for name in names) for group, names in STAGE_GROUPS.items()
            },
            "masks_per_level": counts[precision][-1],
            "masks_per_level_mean": [float(np.mean(column)) for column in zip(*counts[precision])],
            "per_level_peak_mib": round(max(per_level_peaks), 1) if per_level_peaks else None,
            "one_pass_peak_mib": round(max(peaks[precision]), 1),
            "one_pass_working_peak_mib": round(max(working[precision]), 1),
        }
        if precision in streams:
            row.update(streams[precision])
        if precision == "fp32" and differing:
            row.update(
                differing_pixels=int(sum(differing)),
                differing_images=int(sum(d > 0 for d in differing)),
                compared_pixels=pixels,
            )
        if precision != "fp32" and "fp32" in labels_of:
            row["agreement_with_fp32"] = agreement(labels_of["fp32"], labels_of[precision])
        rows.append(row)
    return {"rows": rows}


def stream_seconds(images, one_pass, precision: str, labels_alone: list, together=None) -> dict:
    """Seconds per image over all ``images`` one after another, and with two threads (what the cache build does:
    the device works on one image while the host works on the other). Each image has its generator (the
    stand-in belongs to one image), all sharing one encoder lock as one generator's calls do; each image's labels
    are checked against those it got alone. ``together(name)`` returns when every process of ``--processes`` has
    reached the stream ``name``, so that they stream at the same time; each stream's wall-clock start and end are
    kept for the parent's count."""
    from concurrent.futures import ThreadPoolExecutor

    generators = [one_pass(image, maps, seed, precision) for seed, image, maps in images]
    model_steps = [getattr(g.steps, "model_steps", g.steps) for g in generators]  # the stand-in's SAM, or SAM's
    for steps in model_steps[1:]:
        if steps is not None:
            steps.encoder_lock = model_steps[0].encoder_lock

    def label(i: int):
        return generators[i].label_images(images[i][1])

    result = {}
    for name, threads in (("stream_one_at_a_time_s", 1), ("stream_overlapped_s", 2)):
        if together is not None:
            together(name)
        before = reset_peak()
        result[name.replace("_s", "_began")] = time.time()
        start = time.perf_counter()
        with ThreadPoolExecutor(max_workers=threads) as pool:
            labels = list(pool.map(label, range(len(images))))
        synchronize()
        result[name] = (time.perf_counter() - start) / len(images)
        result[name.replace("_s", "_ended")] = time.time()
        result[name.replace("_s", "_peak_mib")] = round(peak_mib(), 1)
        result[name.replace("_s", "_working_peak_mib")] = round(peak_mib() - before, 1)  # less the images' stand-ins
        same = all(np.array_equal(a, b) for got, want in zip(labels, labels_alone) for a, b in zip(got, want))
        result[name.replace("_s", "_labels_as_alone")] = same
    return result


def decoder_agreement(sam, image: np.ndarray, precision: str, settings: dict) -> dict:
    """The model's own masks at ``precision`` against fp32's, prompt by prompt: every point of the grid on the whole
    image, all three outputs, before any filter (so that random weights give as many masks as trained ones)."""
    import torch
    from segment_anything import SamPredictor
    from segment_anything.utils.amg import build_point_grid, calculate_stability_score

    from votesplat_ns.core.sam_masks import SamSteps

    points = build_point_grid(settings["points_per_side"]) * np.array(image.shape[:2])[None, ::-1]
    steps = {p: SamSteps(SamPredictor(sam), p) for p in ("fp32", precision)}
    states = {p: steps[p].encode_crops([image])[0] for p in steps}
    mask_iou, iou_change, stability_change, iou_flips, stability_flips = [], [], [], [], []
    batch = settings["points_per_batch"]
    for start in range(0, len(points), batch):
        decoded = {p: step.decode_points(states[p], points[start : start + batch]) for p, step in steps.items()}
        iou_a, iou_b = decoded["fp32"][1].flatten(), decoded[precision][1].flatten()
        iou_change.append((iou_a - iou_b).abs())
        iou_flips.append((iou_a > settings["pred_iou_thresh"]) != (iou_b > settings["pred_iou_thresh"]))
        for rows in torch.split(torch.arange(len(iou_a), device=iou_a.device), 64):  # 64 masks at a time: 4K fits
            masks, stability = {}, {}
            for p, step in steps.items():
                logits = step.upscale_masks(states[p], decoded[p][0].flatten(0, 1)[rows])
                stability[p] = calculate_stability_score(logits, step.mask_threshold, 1.0)
                masks[p] = logits > step.mask_threshold
                del logits
            a, b = masks["fp32"], masks[precision]
            union = (a | b).flatten(1).sum(1)
            overlap = (a & b).flatten(1).sum(1)
            mask_iou.append(
                torch.where(union > 0, overlap / union.clamp(min=1), torch.ones_like(overlap, dtype=torch.float))
            )
            stability_change.append((stability["fp32"] - stability[precision]).abs())
            threshold = settings["stability_score_thresh"]
            stability_flips.append((stability["fp32"] >= threshold) != (stability[precision] >= threshold))
    mask_iou_all = torch.cat(mask_iou).double().cpu().numpy()
    return {
        "masks": int(mask_iou_all.size),
        "mask_iou_mean": float(mask_iou_all.mean()),
        "mask_iou_p05": float(np.quantile(mask_iou_all, 0.05)),
        "mask_iou_min": float(mask_iou_all.min()),
        "share_mask_iou_ge_0_9": float(np.mean(mask_iou_all >= 0.9)),
        "share_mask_iou_ge_0_99": float(np.mean(mask_iou_all >= 0.99)),
        "pred_iou_abs_change_mean": float(torch.cat(iou_change).mean()),
        "pred_iou_abs_change_max": float(torch.cat(iou_change).max()),
        "stability_abs_change_mean": float(torch.cat(stability_change).nan_to_num().mean()),
        "share_pred_iou_filter_flips": float(torch.cat(iou_flips).float().mean()),
        "share_stability_filter_flips": float(torch.cat(stability_flips).float().mean()),
    }


def encoder_seconds(sam, image: np.ndarray, precision: str) -> float:
    """One encoder pass on the whole image, after a warm-up pass."""
    from segment_anything import SamPredictor

    from votesplat_ns.core.sam_masks import SamSteps

    steps = SamSteps(SamPredictor(sam), precision)
    steps.encode_crops([image])
    return timed(steps.encode_crops, [image])[1]


def bench(model_type: str, image: np.ndarray, args, settings, write) -> list:
    import torch
    from sam_stand_in import scene  # pyright: ignore[reportMissingImports]
    from segment_anything import sam_model_registry

    torch.manual_seed(0)
    sam = None if args.no_model else sam_model_registry[model_type](checkpoint=None).to(args.device).eval()
    rows = []
    levels = tuple(args.levels)
    for workload in args.workloads:
        images: List[Tuple[int, np.ndarray, Any]]
        if workload == "random":
            images = [(0, image, None)]
        else:
            seeds = range(args.first_seed, args.first_seed + args.images)
            images = [(seed, *scene(args.height, args.width, seed=seed, fine_cells=args.cells)) for seed in seeds]
        first_image = images[0][1]
        result = bench_workload(sam, workload, images, levels, args, settings)
        for row in result["rows"]:
            row.update(model_type=model_type)
            if sam is not None:
                with torch.no_grad():
                    row["encoder_one_pass_s"] = encoder_seconds(sam, first_image, row["precision"])
                    if row["precision"] != "fp32" and args.decoder_agreement:
                        row["decoder_agreement_with_fp32"] = decoder_agreement(
                            sam, first_image, row["precision"], settings
                        )
            rows.append(row)
            print(json.dumps(row), flush=True)
        write(rows)
    del sam
    reset_peak()
    return rows


def decoder_modes(device: str, prompts: int, repeats: int = 10) -> List[dict]:
    """The prompt decoder alone (``core/sam_decoder.py``): every mode on ``prompts`` point prompts of one image,
    SAM's decoder sizes with random weights moved off their initial values, fp32 and (CUDA) bf16: ms per call and
    how far each mode's outputs are from segment_anything's ``MaskDecoder`` in the same precision."""
    from contextlib import nullcontext

    import torch
    from segment_anything.modeling import MaskDecoder, PromptEncoder, TwoWayTransformer

    from votesplat_ns.core.sam_decoder import decode_multimask
    from votesplat_ns.core.sam_masks import _compiled_decode_multimask

    torch.manual_seed(0)
    prompt_encoder = PromptEncoder(
        embed_dim=256, image_embedding_size=(64, 64), input_image_size=(1024, 1024), mask_in_chans=16
    ).to(device)
    transformer = TwoWayTransformer(depth=2, embedding_dim=256, mlp_dim=2048, num_heads=8)
    decoder = MaskDecoder(num_multimask_outputs=3, transformer=transformer, transformer_dim=256).to(device).eval()
    with torch.no_grad():
        for parameter in [*decoder.parameters(), *prompt_encoder.parameters()]:
            parameter.add_(0.05 * torch.randn_like(parameter))
    embedding = torch.randn(1, 256, 64, 64, device=device)
    points = torch.rand(prompts, 1, 2, device=device) * 1024
    labels = torch.ones(prompts, 1, dtype=torch.int, device=device)
    rows = []
    for precision in ("fp32", "bf16") if device == "cuda" else ("fp32",):
        autocast = torch.autocast(device, dtype=torch.bfloat16) if precision == "bf16" else nullcontext()
        with torch.no_grad(), autocast:
            sparse, dense = prompt_encoder(points=(points, labels), boxes=None, masks=None)
            image_pe = prompt_encoder.get_dense_pe()
            outputs = {}
            runs = [(mode, decode_multimask, mode) for mode in DECODER_MODES]
            if device == "cuda":  # also the default decoder as SamSteps runs it there (compiled at the warm-up)
                runs.append(("folded, compiled", _compiled_decode_multimask(), "folded"))
            for name, decode, mode in runs:
                decode(decoder, embedding, image_pe, sparse, dense, mode)  # warm-up
                if device == "cuda":
                    torch.cuda.synchronize()
                start = time.perf_counter()
                for _ in range(repeats):
                    masks, iou = decode(decoder, embedding, image_pe, sparse, dense, mode)
                if device == "cuda":
                    torch.cuda.synchronize()
                outputs[name] = (masks.float(), iou.float(), (time.perf_counter() - start) / repeats)
        reference_masks, reference_iou, _ = outputs["segment_anything"]
        for mode, (masks, iou, seconds) in outputs.items():
            rows.append(
                {
                    "precision": precision,
                    "decoder": mode,
                    "prompts": prompts,
                    "ms_per_call": round(1000 * seconds, 2),
                    "max_logit_difference": float((masks - reference_masks).abs().max()),
                    "share_sign_changed": float(((masks > 0) != (reference_masks > 0)).float().mean()),
                    "max_iou_difference": float((iou - reference_iou).abs().max()),
                }
            )
    return rows


def meet(folder: Path, name: str, index: int, timeout: float = 1800.0) -> None:
    """Mark this copy as at ``name`` and wait for the other copies (the folder's ``copies`` file holds their count)."""
    (folder / f"{name}.{index}").touch()
    copies = int((folder / "copies").read_text())
    deadline = time.monotonic() + timeout
    while len(list(folder.glob(f"{name}.*"))) < copies:
        if time.monotonic() > deadline:
            raise SystemExit(f"bench_sam copy {index}: the other copies did not reach {name} in {timeout:.0f} s")
        time.sleep(0.01)


def run_copies(processes: int, argv: List[str], json_path: Optional[Path]) -> int:
    """``processes`` copies of this bench (``argv``, with ``--processes 1`` and a ``--json`` of their own added: the
    last value of a flag wins) on the device at once, each stream started together; prints, per stream, the seconds
    per image of all copies: their images over the time from the first copy's start to the last one's end."""
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        meeting = Path(folder)
        (meeting / "copies").write_text(str(processes))
        children = []
        for index in range(processes):
            command = [
                sys.executable,
                __file__,
                *argv,
                "--processes",
                "1",
                "--json",
                str(meeting / f"copy_{index}.json"),
            ]
            command += ["--together-in", folder, "--copy-index", str(index)]
            children.append(subprocess.Popen(command))
        codes = [child.wait() for child in children]
        if any(codes):
            print(f"bench_sam: copies exited with {codes}", file=sys.stderr)
            return 1
        records = [json.loads((meeting / f"copy_{index}.json").read_text()) for index in range(processes)]
    together: List[dict] = []
    for rows in zip(*(record["rows"] for record in records)):
        row = {key: rows[0][key] for key in ("model_type", "workload", "precision", "images")}
        row["processes"] = processes
        for name in ("stream_one_at_a_time", "stream_overlapped"):
            if f"{name}_s" not in rows[0]:
                continue
            span = max(r[f"{name}_ended"] for r in rows) - min(r[f"{name}_began"] for r in rows)
            row[f"{name}_all_copies_s"] = span / sum(r["images"] for r in rows)
            row[f"{name}_each_copy_s"] = [r[f"{name}_s"] for r in rows]
            row[f"{name}_start_spread_s"] = max(r[f"{name}_began"] for r in rows) - min(
                r[f"{name}_began"] for r in rows
            )
            row[f"{name}_labels_as_alone"] = all(r[f"{name}_labels_as_alone"] for r in rows)
        together.append(row)
        print(json.dumps(row), flush=True)
    if json_path is not None:
        json_path.write_text(json.dumps({"copies": records, "rows": together}, indent=2))
    print(f"\n{processes} copies on the device at once: seconds per image of all copies together (images / span)")
    print("| model | workload | precision | images per copy | in a row, one / two at a time | each copy's own |")
    print("|---|---|---|---|---|---|")
    for row in together:
        print(
            f"| {row['model_type']} | {row['workload']} | {row['precision']} | {row['images']} | "
            f"{row['stream_one_at_a_time_all_copies_s']:.3f} / {row['stream_overlapped_all_copies_s']:.3f} | "
            f"{[round(v, 3) for v in row['stream_one_at_a_time_each_copy_s']]} / "
            f"{[round(v, 3) for v in row['stream_overlapped_each_copy_s']]} |"
        )
    return 0


def main(argv=None) -> int:
    from votesplat_ns.core.sam_masks import DEFAULT_POINTS_PER_BATCH, SAM_PRECISIONS

    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("--image", type=Path, default=None, help="a photo to segment (default: a smooth random image)")
    parser.add_argument("--model-types", nargs="+", default=["vit_h"], choices=["vit_b", "vit_l", "vit_h"])
    parser.add_argument("--workloads", nargs="+", default=["stand-in", "random"], choices=["stand-in", "random"])
    parser.add_argument("--levels", nargs="+", default=["s", "m", "l"], choices=["default", "s", "m", "l"])
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1080)
    parser.add_argument("--4k", dest="four_k", action="store_true", help="3840 x 2160, one pass only")
    parser.add_argument("--images", type=int, default=3, help="stand-in scenes (each compared with the per_level path)")
    parser.add_argument("--first-seed", type=int, default=0, help="seed of the first stand-in scene")
    parser.add_argument("--cells", type=int, default=300, help="finest segments per stand-in scene")
    parser.add_argument("--repeats", type=int, default=2, help="timed one-pass runs per image (0: one, no split)")
    parser.add_argument("--one-pass-only", action="store_true", help="skip the per-level path (no comparison)")
    parser.add_argument("--no-model", action="store_true", help="stand-in without a SAM model (identity check only)")
    parser.add_argument("--precision", nargs="+", default=["fp32"], choices=list(SAM_PRECISIONS))
    parser.add_argument(
        "--no-decoder-agreement",
        dest="decoder_agreement",
        action="store_false",
        help="skip the prompt-by-prompt comparison of each precision's masks with fp32's",
    )
    parser.add_argument(
        "--decoder", default=DEFAULT_DECODER, choices=list(DECODER_MODES), help="the one-pass path's mask decoder"
    )
    parser.add_argument(
        "--no-compile",
        dest="compile_decoder",
        action="store_false",
        help="the one-pass path's decoder and stability scores uncompiled on a GPU (compiled by default, as `votesplat "
        "masks` runs them)",
    )
    parser.add_argument("--points-per-batch", type=int, default=DEFAULT_POINTS_PER_BATCH, help="both paths")
    parser.add_argument("--crops-per-encoder-pass", type=int, default=None, help="default: 1 in fp32, else all")
    parser.add_argument("--points-per-side", type=int, default=LANGSPLAT["points_per_side"])
    parser.add_argument("--pred-iou-thresh", type=float, default=LANGSPLAT["pred_iou_thresh"])
    parser.add_argument("--stability-score-thresh", type=float, default=LANGSPLAT["stability_score_thresh"])
    parser.add_argument("--crop-n-layers", type=int, default=LANGSPLAT["crop_n_layers"])
    parser.add_argument("--device", default=None, help="default: cuda if present, else cpu")
    parser.add_argument(
        "--stream",
        action="store_true",
        help="also time the images one after another and two at a time (host part overlapping the device part)",
    )
    parser.add_argument(
        "--processes",
        type=int,
        default=1,
        help="with --stream: run this many copies of the bench on the device at once, their streams started "
        "together, and report the images per second of all of them (each its own interpreter, as "
        "`votesplat masks --processes-per-gpu` runs them)",
    )
    parser.add_argument("--together-in", type=Path, default=None, help=argparse.SUPPRESS)  # a copy's meeting folder
    parser.add_argument("--copy-index", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument(
        "--decoder-only", action="store_true", help="time the prompt decoder's modes alone (points-per-batch prompts)"
    )
    args = parser.parse_args(argv)
    import torch

    if args.decoder_only:
        device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
        print(
            "| precision | decoder | prompts | ms per call | max logit difference | share of signs changed | max IoU difference |"
        )
        print("|---|---|---|---|---|---|---|")
        for row in decoder_modes(device, args.points_per_batch):
            print(
                f"| {row['precision']} | {row['decoder']} | {row['prompts']} | {row['ms_per_call']:.2f} | "
                f"{row['max_logit_difference']:.2g} | {row['share_sign_changed']:.2g} | {row['max_iou_difference']:.2g} |"
            )
        return 0

    if args.processes > 1:
        if not args.stream:
            parser.error("--processes counts the streams: pass --stream")
        return run_copies(args.processes, list(sys.argv[1:] if argv is None else argv), args.json)
    args.together = None
    if args.together_in is not None:
        args.together = lambda name: meet(args.together_in, name, args.copy_index)
    if args.four_k:
        args.width, args.height, args.one_pass_only = 3840, 2160, True
    if args.no_model and "random" in args.workloads:
        parser.error("--no-model leaves only the stand-in workload: pass --workloads stand-in")
    settings = {
        **LANGSPLAT,
        "points_per_side": args.points_per_side,
        "points_per_batch": args.points_per_batch,
        "pred_iou_thresh": args.pred_iou_thresh,
        "stability_score_thresh": args.stability_score_thresh,
        "crop_n_layers": args.crop_n_layers,
    }
    args.device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    if args.image is not None and not args.image.is_file():
        parser.error(f"{args.image} is not a file; pass an image or leave --image out")
    image = load_image(args.image, args.width, args.height)
    gpu = torch.cuda.get_device_name() if args.device == "cuda" else "cpu"

    def write(rows):
        if args.json is None:
            return
        from votesplat_ns.core.ply_io import atomic_write

        record = {"device": gpu, "width": args.width, "height": args.height, "settings": settings, "rows": rows}
        with atomic_write(args.json, "w") as handle:
            json.dump(record, handle, indent=2)

    rows: List[dict] = []
    for model_type in args.model_types:
        rows += bench(model_type, image, args, settings, lambda more: write(rows + more))
    write(rows)
    print(
        f"\nSAM masks, {'the stand-in alone' if args.no_model else 'random weights'}, {args.width}x{args.height}, levels {'/'.join(args.levels)}, "
        f"{args.points_per_side}x{args.points_per_side} points, {args.crop_n_layers} crop layer(s), "
        f"{args.points_per_batch} prompts per decoder call, {gpu}; one pass: median of {max(1, args.repeats)} "
        "(after a warm-up on the first image on a GPU); per level: one run per stand-in image"
    )
    print(
        "| model | workload | precision | images | per level (s/image) | one pass (s/image) | masks per level | "
        "differing pixels (fp32 vs per level) | matched IoU vs fp32: mean, share >= 0.9 | "
        "peak MiB per level / one pass (one pass's own) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        per_level = f"{row['per_level_s']:.2f}" if row["per_level_s"] is not None else "-"
        differ = f"{row['differing_pixels']} of {row['compared_pixels']}" if "differing_pixels" in row else "-"
        match = row.get("agreement_with_fp32")
        matched = (
            f"{match['matched_iou_mean']:.4f}, {match['share_iou_ge_0_9']:.3f}"
            if match and match["matched_iou_mean"] is not None
            else "-"
        )
        print(
            f"| {row['model_type']} | {row['workload']} | {row['precision']} | {row['images']} | {per_level} | "
            f"{row['one_pass_s']:.3f} | {row['masks_per_level']} | {differ} | {matched} | "
            f"{row['per_level_peak_mib']} / {row['one_pass_peak_mib']} ({row['one_pass_working_peak_mib']}) |"
        )
    agreeing = [row for row in rows if "decoder_agreement_with_fp32" in row]
    if agreeing:
        print(
            "\nthe model's own masks against fp32's, prompt by prompt (whole image, every grid point, all three outputs, "
            "before the filters)"
        )
        print(
            "| model | workload image | precision | masks | mask IoU mean | 5th percentile | share >= 0.99 | "
            "predicted IoU change, mean / max | filter decisions changed: predicted IoU, stability |"
        )
        print("|---|---|---|---|---|---|---|---|---|")
        for row in agreeing:
            d = row["decoder_agreement_with_fp32"]
            print(
                f"| {row['model_type']} | {row['workload']} | {row['precision']} | {d['masks']} | "
                f"{d['mask_iou_mean']:.4f} | {d['mask_iou_p05']:.4f} | {d['share_mask_iou_ge_0_99']:.3f} | "
                f"{d['pred_iou_abs_change_mean']:.4f} / {d['pred_iou_abs_change_max']:.4f} | "
                f"{d['share_pred_iou_filter_flips']:.4f}, {d['share_stability_filter_flips']:.4f} |"
            )
    streamed = [row for row in rows if "stream_overlapped_s" in row]
    if streamed:
        print("\nall images in a row (s/image): one at a time, and two at a time as the cache build runs them")
        print(
            "| model | workload | precision | images | one at a time | overlapped | labels as alone | "
            "peak GPU MiB (the pass's own), one / two at a time |"
        )
        print("|---|---|---|---|---|---|---|---|")
        for row in streamed:
            same = row["stream_one_at_a_time_labels_as_alone"] and row["stream_overlapped_labels_as_alone"]
            print(
                f"| {row['model_type']} | {row['workload']} | {row['precision']} | {row['images']} | "
                f"{row['stream_one_at_a_time_s']:.3f} | {row['stream_overlapped_s']:.3f} | {same} | "
                f"{row['stream_one_at_a_time_peak_mib']} ({row['stream_one_at_a_time_working_peak_mib']}) / "
                f"{row['stream_overlapped_peak_mib']} ({row['stream_overlapped_working_peak_mib']}) |"
            )
    print("\none pass per stage (s/image, median; the encoder stage is every crop's pass)")
    groups = list(STAGE_GROUPS)
    names = [name for group in STAGE_GROUPS.values() for name in group] + ["stand_in_own"]
    print(
        "| model | workload | precision | one encoder pass, whole image | "
        + " | ".join(groups)
        + " | "
        + " | ".join(names)
        + " |"
    )
    print("|---|---|---|---|" + "---|" * (len(groups) + len(names)))
    for row in rows:
        grouped = " | ".join(f"{row['one_pass_stage_groups_s'][group]:.3f}" for group in groups)
        split = " | ".join(f"{row['one_pass_stages_s'].get(name, 0.0):.3f}" for name in names)
        encoder = f"{row['encoder_one_pass_s']:.3f}" if "encoder_one_pass_s" in row else "-"
        print(f"| {row['model_type']} | {row['workload']} | {row['precision']} | {encoder} | {grouped} | {split} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
