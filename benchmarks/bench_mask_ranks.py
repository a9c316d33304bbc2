"""Images per second of ``votesplat masks`` on 1 and on N GPUs (``--num-gpus``), with K processes on each
(``--processes-per-gpu``), on the same images, and whether the caches they make hold the same entries.

    python benchmarks/bench_mask_ranks.py --data <nerfstudio dataset> --ranks 1 2 --json out.json
    python benchmarks/bench_mask_ranks.py --data <dataset> --ranks 1 --processes-per-gpu 1 2   # one GPU, 1 and 2
    python benchmarks/bench_mask_ranks.py --data <dataset> --source dataset --ranks 1 2 --sam-device cpu   # plumbing, CPU

Each pair of counts runs the real command (``votesplat masks --source sam --num-gpus N --processes-per-gpu K``) in
a subprocess, into a cache of its own, so process start, the SAM model's load on every rank and the cache writes are
all counted;
the command's own line ``made K in T s (X images/s, N processes)`` gives the build's time (from the first image's
hash to the last entry written; the dataset parse before it is the same for every N). Without
``--sam-checkpoint`` a RANDOMLY INITIALISED model of ``--sam-model-type`` is saved first and used by every run:
the encoder and decoder cost what real weights cost, fewer masks survive the filters. Then every entry of each
cache is compared with the 1-rank cache: the labels file byte for byte, the record's arrays value for value
(its zip's dates aside). Give enough images that a rank's start (its imports, the model's load, the decoder's
compilation on a GPU: some 30 s) is a small part of its share: ``--copies K`` makes a capture of K times the
dataset's images, copy c of each image shifted by c pixels (a different image, the same content).
"""

from __future__ import annotations

import argparse
import json
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
# the console script beside this interpreter (a venv), else the one on PATH (a --target install, as on the GPU host)
VOTESPLAT = Path(sys.executable).parent / "votesplat"
if not VOTESPLAT.exists() and shutil.which("votesplat"):
    VOTESPLAT = Path(shutil.which("votesplat") or "votesplat")
MADE = re.compile(r"made (\d+) in ([0-9.]+) s \(([0-9.]+) images/s, (\d+) process")


def random_checkpoint(folder: Path, model_type: str, seed: int = 0) -> Path:
    """A randomly initialised SAM of ``model_type``, saved as a checkpoint file."""
    import torch
    from segment_anything import sam_model_registry

    path = folder / f"random_sam_{model_type}_seed{seed}.pth"
    if not path.is_file():
        torch.manual_seed(seed)
        torch.save(sam_model_registry[model_type](checkpoint=None).state_dict(), path)
    return path


def copied_capture(data: Path, copies: int, folder: Path, height: Optional[int] = None) -> Path:
    """``data`` with each frame's image ``copies`` times (copy c rolled by c pixels), resized to ``height`` pixels
    high (the intrinsics scaled with it) when given, its other files shared."""
    from PIL import Image

    meta = json.loads((data / "transforms.json").read_text())
    out = folder / (f"{data.name}_x{copies}" + (f"_{height}p" if height else ""))
    if out.exists():
        shutil.rmtree(out)
    (out / "images").mkdir(parents=True)
    scale = height / float(meta["h"]) if height else 1.0
    for key in ("fl_x", "fl_y", "cx", "cy"):
        if key in meta:
            meta[key] = meta[key] * scale
    for key in ("w", "h"):
        if key in meta:
            meta[key] = int(round(meta[key] * scale))
    frames, names = [], {}
    for frame in meta["frames"]:
        picture = Image.open(data / frame["file_path"]).convert("RGB")
        if height:
            picture = picture.resize((int(round(picture.width * scale)), height), Image.Resampling.BICUBIC)
        image = np.asarray(picture)
        for copy in range(copies):
            name = f"images/{Path(frame['file_path']).stem}_c{copy}.png"
            Image.fromarray(np.roll(image, copy, axis=1)).save(out / name)
            frames.append({**frame, "file_path": name})
            names.setdefault(Path(frame["file_path"]).name, []).append(Path(name).name)
    for key in ("train_filenames", "val_filenames", "test_filenames"):
        if key in meta:  # the splits name the copies of their images
            meta[key] = [f"images/{copy}" for listed in meta[key] for copy in names.get(Path(listed).name, [])]
    meta["frames"] = frames
    for entry in data.iterdir():  # the mask, depth and point files the frames name
        if entry.name not in ("images", "transforms.json"):
            (out / entry.name).symlink_to(entry.resolve())
    (out / "transforms.json").write_text(json.dumps(meta))
    return out


def run_masks(args, ranks: int, cache: Path, checkpoint: Optional[Path], per_gpu: int = 1) -> Dict[str, object]:
    command = [str(VOTESPLAT), "masks", "--data", str(args.data), "--cache-dir", str(cache), "--source", args.source]
    command += ["--num-gpus", str(ranks), "--processes-per-gpu", str(per_gpu)]
    if args.source == "sam":
        command += ["--sam-checkpoint", str(checkpoint), "--sam-model-type", args.sam_model_type]
        command += ["--sam-max-long-side", str(args.max_long_side)]
    if args.sam_device:
        command += ["--sam-device", args.sam_device]
    command += shlex.split(args.masks_args)
    wall = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - wall
    if result.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{result.stderr[-3000:]}")
    found = MADE.search(result.stdout)
    row: Dict[str, object] = {"ranks": ranks, "processes_per_gpu": per_gpu, "command_wall_s": round(wall, 2)}
    if found:
        made, seconds = int(found.group(1)), float(found.group(2))
        row.update(images=made, build_s=round(seconds, 2), images_per_s=round(made / seconds, 3))
    return row


def entry_dir(cache: Path) -> Path:
    (folder,) = [path for path in cache.iterdir() if path.is_dir()]
    return folder


def same_entries(first: Path, second: Path) -> Dict[str, int]:
    """How many entries of ``first`` ``second`` holds identically, and how many differ or are missing."""
    keys = sorted(path.name[: -len(".votes.npz")] for path in first.glob("*.votes.npz"))
    same = 0
    for key in keys:
        labels = second / f"{key}.labels.npy"
        if not labels.is_file() or labels.read_bytes() != (first / f"{key}.labels.npy").read_bytes():
            continue
        with np.load(first / f"{key}.votes.npz") as a, np.load(second / f"{key}.votes.npz") as b:
            if sorted(a.files) == sorted(b.files) and all(
                np.array_equal(a[name], b[name], equal_nan=a[name].dtype.kind == "f") for name in a.files
            ):
                same += 1
    return {"entries": len(keys), "identical": same, "different_or_missing": len(keys) - same}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="a nerfstudio dataset (transforms.json)")
    parser.add_argument(
        "--ranks", type=int, nargs="+", default=[1, 2], help="--num-gpus values; the first is the baseline"
    )
    parser.add_argument(
        "--processes-per-gpu",
        type=int,
        nargs="+",
        default=[1],
        help="--processes-per-gpu values, each run with each --ranks value (the first pair is the baseline)",
    )
    parser.add_argument("--source", choices=["sam", "dataset", "folder"], default="sam")
    parser.add_argument("--sam-checkpoint", type=Path, default=None, help="default: a random-init model, saved first")
    parser.add_argument("--sam-model-type", default="vit_h")
    parser.add_argument("--sam-device", default=None, help="cpu: the ranks are CPU processes")
    parser.add_argument("--max-long-side", type=int, default=1080)
    parser.add_argument("--work-dir", type=Path, default=Path("build/bench_mask_ranks"))
    parser.add_argument("--copies", type=int, default=1, help="each image this many times (shifted copies)")
    parser.add_argument("--height", type=int, default=None, help="resize the images to this height (e.g. 1080)")
    parser.add_argument(
        "--masks-args",
        default="",
        help="more flags for every votesplat masks run, e.g. '--sam-precision fp32' (random weights keep at most a "
        "mask or two per image whatever the filters: the host's share of a real capture is not in these runs)",
    )
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()

    args.work_dir.mkdir(parents=True, exist_ok=True)
    if args.copies > 1 or args.height:
        args.data = copied_capture(args.data, args.copies, args.work_dir, args.height)
    checkpoint = None
    if args.source == "sam":
        checkpoint = args.sam_checkpoint or random_checkpoint(args.work_dir, args.sam_model_type)
    rows: List[Dict[str, object]] = []
    caches = []
    for ranks in args.ranks:
        for per_gpu in args.processes_per_gpu:
            cache = args.work_dir / f"cache_{ranks}_gpus_{per_gpu}_each"
            if cache.exists():
                shutil.rmtree(cache)
            rows.append(run_masks(args, ranks, cache, checkpoint, per_gpu))
            caches.append(entry_dir(cache))
            print(json.dumps(rows[-1]), flush=True)
    base = rows[0]
    for row, cache in zip(rows, caches):
        row["identical_to_baseline"] = same_entries(caches[0], cache)
        if "images_per_s" in row and "images_per_s" in base:
            speedup = float(row["images_per_s"]) / float(base["images_per_s"])  # type: ignore[arg-type]
            row["speedup"] = round(speedup, 3)
            row["speedup_per_gpu"] = round(speedup * int(base["ranks"]) / int(row["ranks"]), 3)  # type: ignore[arg-type]
    result = {"data": str(args.data), "source": args.source, "model_type": args.sam_model_type, "runs": rows}
    print(json.dumps(result, indent=2))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
