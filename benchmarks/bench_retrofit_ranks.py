"""A data-parallel retrofit (``ns/data_parallel.py``) on 1 and on N ranks with the same number of views seen: wall
time, vote error and instance mIoU of each, and their ratios and differences.

    python benchmarks/bench_retrofit_ranks.py --data build/family_test/family_2054 --base-steps 1500 \
        --gaussians 2000000 --views 2400 --ranks 1 2 --json out.json      # CUDA: one GPU per rank, NCCL
    python benchmarks/bench_retrofit_ranks.py --device cpu                # toy size on the CPU (gloo, torchrun)

The first command is the measurement on a host with two H100s, after ``bash scripts/gpu/run.sh setup`` (carry
``.whl``, ``.gpu/gsplat_build.tar.gz`` and ``build/family_test``); BENCHMARKS.md "Several GPUs" has its figures.
``setup_s``, ``step_ms`` and ``tail_s`` show where each run's time went: the ranks of a multi-GPU run each import
nerfstudio, read the PLY and join NCCL, so the steps must outweigh that set-up for the wall time to fall.

Steps:

1. **Base scene.** ``--base-run <config.yml>`` reuses a trained run; otherwise the scene is trained once in this
   process without votes (``--base-steps``, vote losses off, ``num_downscales 0``) into
   ``<work-dir>/<scene>/base_<steps>`` and reused by later calls. Its training builds the vote cache
   (``<work-dir>/<scene>/vote_cache``, masks from the dataset's transforms.json, ``--levels``) that every retrofit
   then reads, so no timed run makes masks.
2. **Retrofit source.** The base run's Gaussians, copied up to ``--gaussians`` (``bench_clustering.upsampled_scene``:
   copies jittered within the original's extent and shrunk to fill it; 0 keeps the trained count), written as a
   standard 3DGS PLY beside the base run's config (``scene_<count>.ply``, reused), so that the vote steps, whose
   cost grows with the Gaussians, outweigh a run's set-up.
3. **Retrofits.** For each count R of ``--ranks``, a real ``ns-train votesplat --pipeline.model.retrofit-from
   <ply>`` in a subprocess of ``--views / R`` steps (every retrofit step is one view per rank, so every run sees
   ``--views`` views), ``--machine.seed``, no intermediate evaluation or checkpoint. R > 1 launches through
   nerfstudio (``--machine.num-devices R``: one process per GPU, NCCL) or, with ``--launcher torchrun`` and always on
   the CPU (``--machine.device-type cpu``: nerfstudio's launch asserts CUDA for several devices), through
   ``python -m torch.distributed.run --standalone --nproc-per-node R`` (gloo on the CPU).
   ``wall_s`` is the subprocess's wall time, ns-train start to exit (set-up, the PLY read on every rank, the steps,
   the end-of-training foreground pass, the checkpoint).
4. **Scores** of each run's checkpoint, in a process of its own (side by side, one GPU each, when there are as
   many GPUs as runs):

   * ``vote_error_px``: the mean, over ``--error-views`` evenly spaced training views and over the vote levels,
     of ``VoteSplatModel.vote_pixel_error``: the L1 distance in pixels (full training resolution) between the
     rendered vote and the 2D vote (its mask's centroid) at every pixel with a vote; what the vote loss
     trains, measured on every pixel rather than on a step's sample. Every run is scored on the same views.
   * ``miou``: ``votesplat eval``'s instance mIoU (``evaluate_run``, held-out views, the training-mask check on as
     for a user; the object-removal check off, it does not enter mIoU), at the first of ``--levels``; over the
     valid views where it reports them.

Printed as a table and written to ``--json`` after every stage. Each run gets the numbers above. Each R > 1 is
compared with the first count of ``--ranks``: ``wall_ratio``, ``steps_ratio`` (the steps alone, steps x
``step_ms``), ``vote_error_diff_px`` and ``vote_error_rel_diff`` (R ranks minus the first, relative to the
first), and ``miou_diff``. A run that fails is recorded with its error and the tail of its log, and the other
runs still go ahead.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

DEMO = ROOT / "votesplat_ns" / "data" / "demo"
STEP_TAG = "Train Iter (time)"  # a scalar nerfstudio logs at every logged step: its event's wall time dates the step
# per device: base steps, Gaussians (0: as trained), views seen, vote pixels per step, error views
DEFAULTS = {
    "cuda": {"base_steps": 2000, "gaussians": 2_000_000, "views": 1600, "vote_pixels": 4096, "error_views": 12},
    "cpu": {"base_steps": 30, "gaussians": 8000, "views": 8, "vote_pixels": 512, "error_views": 2},
}


def console_script(name: str) -> str:
    """The console script beside this interpreter (a venv), else the one on PATH (a --target install)."""
    beside = Path(sys.executable).parent / name
    if beside.exists():
        return str(beside)
    found = shutil.which(name)
    if found is None:
        raise SystemExit(f"bench_retrofit_ranks.py: error: {name} not found beside {sys.executable} or on PATH")
    return found


def level_flags(levels: Sequence[str]) -> List[str]:
    """Masks from the dataset's transforms.json (``<level>_mask_path``), one vote level each."""
    return [
        "--pipeline.datamanager.mask-source",
        "dataset",
        "--pipeline.datamanager.mask-levels",
        *levels,
        "--pipeline.model.vote-levels",
        *levels,
    ]


# ----------------------------------------------------------------------------------------------- base scene


def base_run(args) -> Path:
    """config.yml of the scene trained without votes: ``--base-run``, else one trained earlier, else trained now."""
    from votesplat_ns.ns.method import train_in_process
    from votesplat_ns.ns.run import latest_checkpoint

    if args.base_run is not None:
        return args.base_run
    base_dir = args.scene_dir / f"base_{args.base_steps}"
    for config_path in sorted(base_dir.glob("*/votesplat/run/config.yml")):
        try:
            latest_checkpoint(config_path)
            return config_path
        except ValueError:  # an interrupted training: train again
            pass
    start = time.perf_counter()
    config_path = train_in_process(
        args.data,
        base_dir,
        args.base_steps,
        args.base_steps + 1,  # the votes never start: splatfacto's training (the vote cache is still built)
        args.device,
        "run",
        seed=args.seed,
        datamanager_overrides={"cache_dir": args.cache_dir, "mask_source": "dataset", "mask_levels": args.levels},
        num_downscales=0,
        vote_levels=tuple(args.levels),
        vote_loss_weight=0.0,
        distortion_loss_weight=0.0,
    )
    print(f"base scene: {args.base_steps} steps in {time.perf_counter() - start:.1f} s -> {config_path}", flush=True)
    return config_path


def retrofit_source(base_config: Path, gaussians: int, seed: int) -> Dict[str, object]:
    """The base run's Gaussians (copied up to ``gaussians``, 0: as many as trained) as a 3DGS PLY beside it."""
    from votesplat_ns.core.ply_io import write_gaussian_table
    from votesplat_ns.ns.run import load_run_scene

    start = time.perf_counter()
    scene, _ = load_run_scene(base_config)
    trained = scene.num_gaussians
    count = gaussians or trained
    path = base_config.parent / f"scene_{count}.ply"
    if not path.exists():
        if count != trained:
            from benchmarks.bench_clustering import upsampled_scene

            scene, _ = upsampled_scene(scene, count, seed)
        write_gaussian_table(path, scene.vertex_table())  # the Gaussians only, as a splatfacto export
    return {
        "ply": str(path),
        "trained_gaussians": trained,
        "gaussians": count,
        "ply_s": round(time.perf_counter() - start, 2),
    }


# ----------------------------------------------------------------------------------------------- retrofits


def retrofit_command(args, ranks: int, steps: int, ply: Path, output_dir: Path) -> List[str]:
    ns_train = console_script("ns-train")
    if ranks == 1:
        command = [ns_train]
    elif args.launcher == "torchrun":
        command = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={ranks}"]
        command.append(ns_train)
    else:
        command = [ns_train]
    never = str(10 * steps)  # no evaluation and no checkpoint before the last step
    command += [
        "votesplat",
        "--data",
        str(args.data),
        "--output-dir",
        str(output_dir),
        "--experiment-name",
        f"ranks_{ranks}",
        "--timestamp",
        "run",
        "--max-num-iterations",
        str(steps),
        "--steps-per-save",
        never,
        "--steps-per-eval-image",
        never,
        "--steps-per-eval-batch",
        "0",
        "--steps-per-eval-all-images",
        never,
        "--vis",
        "tensorboard",
        "--logging.steps-per-log",
        str(10 if steps >= 100 else 1),
        "--machine.seed",
        str(args.seed),
        "--machine.device-type",
        args.device,
        "--pipeline.model.retrofit-from",
        str(ply),
        "--pipeline.model.num-downscales",
        "0",
        "--pipeline.model.vote-pixels-per-step",
        str(args.vote_pixels),
        "--pipeline.datamanager.cache-dir",
        str(args.cache_dir),
        *level_flags(args.levels),
    ]
    if ranks > 1 and args.launcher == "nerfstudio":
        command += ["--machine.num-devices", str(ranks)]
    return command


def step_split(run_dir: Path, started: float, ended: float) -> Dict[str, float]:
    """Where a run's wall time went, from the wall times of the steps rank 0 logged to tensorboard: ``setup_s``
    (process start to the first logged step's end), ``step_ms`` (mean step between the first and the second-to-last
    logged step) and ``tail_s`` (from there to the exit: the last step, the foreground pass, the checkpoint)."""
    try:
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    except ImportError:
        return {}
    events = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
    events.Reload()
    if STEP_TAG not in events.Tags().get("scalars", []):
        return {}
    logged = events.Scalars(STEP_TAG)
    if len(logged) < 3:
        return {}
    first, before_last = logged[0], logged[-2]
    return {
        "setup_s": round(first.wall_time - started, 2),
        "step_ms": round(1000 * (before_last.wall_time - first.wall_time) / (before_last.step - first.step), 2),
        "tail_s": round(ended - before_last.wall_time, 2),
    }


def run_retrofit(args, ranks: int, ply: Path) -> Dict[str, object]:
    steps = args.views // ranks
    output_dir = args.work_dir / "runs"
    run_dir = output_dir / f"ranks_{ranks}" / "votesplat" / "run"
    if run_dir.exists():
        shutil.rmtree(run_dir)
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    log_path = output_dir / f"ranks_{ranks}.log"
    command = retrofit_command(args, ranks, steps, ply, output_dir)
    row: Dict[str, object] = {"ranks": ranks, "steps": steps, "views_seen": steps * ranks, "log": str(log_path)}
    print(f"ranks {ranks}: {steps} steps each: {' '.join(command)}", flush=True)
    start, started = time.perf_counter(), time.time()
    env = dict(os.environ)
    if args.device == "cpu":  # one thread per process, as torchrun gives each of its ranks
        env["OMP_NUM_THREADS"] = "1"
    with open(log_path, "w") as log:
        try:
            done = subprocess.run(
                command, stdout=log, stderr=subprocess.STDOUT, timeout=args.run_timeout, check=False, env=env
            )
            returncode: Optional[int] = done.returncode
        except subprocess.TimeoutExpired:
            returncode = None
    row["wall_s"] = round(time.perf_counter() - start, 2)
    row.update(step_split(run_dir, started, time.time()))
    checkpoints = sorted((run_dir / "nerfstudio_models").glob("step-*.ckpt"))
    if returncode != 0 or not checkpoints:
        why = f"timed out after {args.run_timeout} s" if returncode is None else f"exit {returncode}"
        tail = log_path.read_text(errors="replace")[-1500:]
        row["error"] = f"ns-train {why}" + ("" if checkpoints else ", no checkpoint") + f"; log tail:\n{tail}"
        return row
    row["config"] = str(run_dir / "config.yml")
    row["checkpoint_step"] = int(checkpoints[-1].stem.split("-")[1])
    return row


# ----------------------------------------------------------------------------------------------- scores


def score_run(config: Path, output: Path, error_views: int, level: str) -> None:
    """Vote error and instance mIoU of one run (this process), written to ``output`` as JSON."""
    import torch

    from votesplat_ns.ns.evaluate import evaluate_run
    from votesplat_ns.ns.run import evenly_spaced, load_run

    start = time.perf_counter()
    result = evaluate_run(config, config.parent / "bench_eval", level=level, ghost_check=False, log=None)
    scores = result.metrics["levels"][level]
    valid = scores.get("miou_valid_views")
    eval_s = time.perf_counter() - start

    start = time.perf_counter()
    pipeline, scene, _ = load_run(config, test_mode="test")
    model, datamanager = pipeline.model, pipeline.datamanager
    views = evenly_spaced(len(datamanager.train_dataset), min(error_views, len(datamanager.train_dataset)))
    errors = []
    with torch.no_grad():
        for index in views:
            camera = datamanager.train_dataset.cameras[index : index + 1]
            errors.append(model.vote_pixel_error(camera, datamanager.vote_batch(index)).cpu())
    per_level = torch.nanmean(torch.stack(errors), dim=0)
    row = {
        "miou": float(scores["miou"] if valid is None else valid),
        "miou_views": "all" if valid is None else "valid",
        "num_predicted_instances": scores.get("num_predicted_instances"),
        "vote_error_px": float(per_level.nanmean()),
        "vote_error_px_per_level": dict(zip(scene.level_names, (round(float(v), 4) for v in per_level))),
        "error_views": [int(v) for v in views],
        "num_gaussians": scene.num_gaussians,
        "eval_s": round(eval_s, 2),
        "vote_error_s": round(time.perf_counter() - start, 2),
    }
    output.write_text(json.dumps(row, indent=2) + "\n")


def score_runs(args, rows: List[Dict[str, object]]) -> None:
    """Score every run that trained, each in a process of its own: side by side on one GPU each when there are
    as many GPUs as runs, else one after the other."""
    import torch

    todo = [row for row in rows if "config" in row]
    gpus = torch.cuda.device_count() if args.device == "cuda" else 0
    side_by_side = gpus >= len(todo) > 1
    started = []
    for slot, row in enumerate(todo):
        output = Path(str(row["config"])).parent / "bench_scores.json"
        output.unlink(missing_ok=True)
        command = [sys.executable, __file__, "--score", str(row["config"]), "--score-output", str(output)]
        command += ["--error-views", str(args.error_views), "--levels", *args.levels]
        env = dict(os.environ)
        if side_by_side:
            env["CUDA_VISIBLE_DEVICES"] = str(slot)
        log = open(Path(str(row["log"])).with_suffix(".score.log"), "w")
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env)
        started.append((row, output, process, log))
        if not side_by_side:
            process.wait()
    for row, output, process, log in started:
        process.wait()
        log.close()
        if process.returncode == 0 and output.is_file():
            row.update(json.loads(output.read_text()))
        else:
            tail = Path(log.name).read_text(errors="replace")[-1500:]
            row["error"] = f"scoring failed (exit {process.returncode}); log tail:\n{tail}"


# ----------------------------------------------------------------------------------------------- report


def compare(rows: List[Dict[str, object]]) -> None:
    """Ratios and differences of every run against the first (the baseline count of ranks)."""
    base = rows[0]
    for row in rows[1:]:
        if "error" in row or "error" in base:
            continue
        row["wall_ratio"] = round(float(row["wall_s"]) / float(base["wall_s"]), 3)  # type: ignore[arg-type]
        if "step_ms" in row and "step_ms" in base:  # the steps alone: steps x ms of one run over the other's
            steps = float(row["steps"]) * float(row["step_ms"]) / (float(base["steps"]) * float(base["step_ms"]))  # type: ignore[arg-type]
            row["steps_ratio"] = round(steps, 3)
        if "miou" in row and "miou" in base:
            row["miou_diff"] = round(float(row["miou"]) - float(base["miou"]), 4)  # type: ignore[arg-type]
        if "vote_error_px" in row and "vote_error_px" in base:
            before, after = float(base["vote_error_px"]), float(row["vote_error_px"])  # type: ignore[arg-type]
            row["vote_error_diff_px"] = round(after - before, 4)
            row["vote_error_rel_diff"] = round((after - before) / before, 4)


COLUMNS = (
    ("ranks", "ranks", "{}"),
    ("steps each", "steps", "{}"),
    ("views seen", "views_seen", "{}"),
    ("wall s", "wall_s", "{:.1f}"),
    ("set-up s", "setup_s", "{:.1f}"),
    ("ms/step", "step_ms", "{:.1f}"),
    ("tail s", "tail_s", "{:.1f}"),
    ("vote error px", "vote_error_px", "{:.3f}"),
    ("mIoU", "miou", "{:.3f}"),
    ("wall ratio", "wall_ratio", "{:.3f}"),
    ("steps ratio", "steps_ratio", "{:.3f}"),
    ("vote error diff", "vote_error_diff_px", "{:+.3f} px"),
    ("vote error rel.", "vote_error_rel_diff", "{:+.2%}"),
    ("mIoU diff", "miou_diff", "{:+.4f}"),
)


def table(rows: List[Dict[str, object]]) -> str:
    """One markdown row per run; a failed run shows its first error line."""
    lines = ["| " + " | ".join(name for name, _, _ in COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for row in rows:
        cells = [fmt.format(row[key]) if key in row else "" for _, key, fmt in COLUMNS]
        if "error" in row:
            cells[7] = "failed: " + str(row["error"]).splitlines()[0]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_json(path: Optional[Path], result: Dict[str, object]) -> None:
    """``result`` to ``path`` (atomically), after every stage: a call cut short keeps what it measured."""
    if path is None:
        return
    from votesplat_ns.core.ply_io import atomic_write

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "w") as handle:
        handle.write(json.dumps(result, indent=2) + "\n")


def parse_args(argv: Optional[List[str]] = None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--data", type=Path, default=None, help="a scene written by votesplat synth (default: the demo)"
    )
    parser.add_argument("--device", choices=["cuda", "cpu"], default="cuda", help="cpu: toy sizes, gloo ranks")
    parser.add_argument("--ranks", type=int, nargs="+", default=[1, 2], help="rank counts; the first is the baseline")
    parser.add_argument("--views", type=int, default=None, help="views seen per run: steps of 1 rank (R ranks: / R)")
    parser.add_argument("--gaussians", type=int, default=None, help="Gaussians of the retrofit source (0: as trained)")
    parser.add_argument("--base-run", type=Path, default=None, help="config.yml of a trained run to retrofit")
    parser.add_argument("--base-steps", type=int, default=None, help="training steps of the base scene")
    parser.add_argument("--vote-pixels", type=int, default=None, help="vote pixels per step")
    parser.add_argument("--error-views", type=int, default=None, help="training views the vote error is taken on")
    parser.add_argument(
        "--levels", nargs="+", default=["instance", "part"], help="mask and vote levels; mIoU at the first"
    )
    parser.add_argument(
        "--launcher", choices=["nerfstudio", "torchrun"], default=None, help="default: nerfstudio on cuda"
    )
    parser.add_argument("--seed", type=int, default=42)
    parser.add_argument("--no-scores", action="store_true", help="time the runs only (no vote error, no mIoU)")
    parser.add_argument("--run-timeout", type=float, default=900.0, help="seconds one ns-train may run")
    parser.add_argument("--work-dir", type=Path, default=Path("build/bench_retrofit_ranks"))
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--score", type=Path, default=None, help=argparse.SUPPRESS)  # one run's scores (a subprocess)
    parser.add_argument("--score-output", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.score is not None:
        return args
    for key, value in DEFAULTS[args.device].items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if args.device == "cpu":
        args.launcher = "torchrun"  # nerfstudio's launch of several devices asserts CUDA
    args.launcher = args.launcher or "nerfstudio"
    args.data = args.data or DEMO
    if not (args.data / "transforms.json").is_file():
        parser.error(f"--data {args.data}: no transforms.json; pass a scene folder written by votesplat synth")
    if args.base_run is not None and not args.base_run.is_file():
        parser.error(f"--base-run {args.base_run}: not found; pass a trained run's config.yml")
    bad = [r for r in args.ranks if r < 1 or args.views % r]
    if bad:
        parser.error(f"--views {args.views} must split evenly over every count of --ranks (not {bad})")
    args.scene_dir = args.work_dir / args.data.resolve().name
    args.cache_dir = (args.scene_dir / "vote_cache").resolve()
    args.work_dir = args.work_dir.resolve()
    return args


def main(argv: Optional[List[str]] = None) -> int:
    args = parse_args(argv)
    if args.score is not None:
        score_run(args.score, args.score_output, args.error_views, args.levels[0])
        return 0
    args.scene_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    base_config = base_run(args)
    source = retrofit_source(base_config, args.gaussians, args.seed)
    print(f"retrofit source: {source}", flush=True)
    rows: List[Dict[str, object]] = []
    result: Dict[str, object] = {
        "data": str(args.data),
        "device": args.device,
        "launcher": args.launcher,
        "base_run": str(base_config),
        "source": source,
        "views": args.views,
        "vote_pixels_per_step": args.vote_pixels,
        "levels": args.levels,
        "seed": args.seed,
        "runs": rows,
    }
    for ranks in args.ranks:
        rows.append(run_retrofit(args, ranks, Path(str(source["ply"]))))
        print(json.dumps({k: v for k, v in rows[-1].items() if k != "error"}), flush=True)
        write_json(args.json, result)
    if not args.no_scores:
        score_runs(args, rows)
    compare(rows)
    result["total_s"] = round(time.perf_counter() - start, 1)
    write_json(args.json, result)
    print(table(rows))
    for row in rows:
        if "error" in row:
            print(f"ranks {row['ranks']}: {row['error']}", file=sys.stderr)
    if args.json:
        print(f"wrote {args.json}")
    return 0 if all("error" not in row for row in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
