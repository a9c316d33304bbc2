"""Choose defaults on a tuning set of scenes: every training variant x every clustering variant.

    python benchmarks/sweep.py --family tuning --masks gt noisy \\
        --train default 'nodist:vote_distortion=none' 'pix0.05:vote_distortion=l1_pixels,distortion_loss_weight=0.05' \\
                'maskonly:dm.border_masks=mask_only' \\
        --cluster fill 'nofill:fill=False' --steps 3000 --vote-start 500 --jobs 16 --work-dir build/sweep

``--masks noisy`` trains on the GT masks with SAM-like errors (``SAM_LIKE_NOISE`` of
votesplat_ns/eval/mask_noise.py, written under ``<work-dir>/<scene>/noisy_masks``).

``--family tuning|test`` takes every scene of that family set (``--family-dir``, default
``build/family_<set>``, written by ``votesplat synth family-set``), checked against the seeds in
votesplat_ns/eval/synthetic/family.py: defaults are chosen on the tuning set only, the test set reports
them. ``--scenes`` takes any votesplat synth folders instead.

A training variant is ``name:field=value,...`` (model config fields; ``dm.<field>`` for the
datamanager's); ``default`` alone trains with the defaults. A clustering variant is
``name:key=value,...`` of :func:`votesplat_ns.core.clustering.cluster_levels` keywords, plus
``mask_check=False`` (the vote clustering alone) and ``mc.<key>=value`` for the training-mask
check (:func:`votesplat_ns.core.mask_consensus.regroup_with_masks`: ``mc.split=False``, ``mc.bisect=False``, ...),
whose whole-object rules (:mod:`votesplat_ns.core.whole_objects`) switch with ``mc.objects=False`` (all), ``mc.join=False``, ``mc.orphans=False``,
``mc.floaters=False``, ``mc.hidden=False``, ``mc.unseen=False``, ``mc.unseen_min_seen=False``, ``mc.contact=False``,
``mc.reach_in_masks=False``, ``mc.rehome=False`` and take ``mc.join_ratio``, ``mc.join_agreement``, ``mc.contact_factor``,
``mc.contact_ratio``, ``mc.hidden_margin``, ``mc.hidden_reach``, ``mc.orphan_cover``, ``mc.join_vote_factor``. Every
(scene, masks, training variant, seed) trains once in its own process (``--jobs`` at a time: a
small scene leaves most of a GPU idle); every clustering variant then scores that run with
``votesplat eval``'s scorer at the instance and the part level. Rows go to
``<work-dir>/sweep.json`` and a table of means over scenes (plus the worst scene) to
``sweep.md``. Scores are mIoU over the views whose reconstruction did not fail, when the scorer
reports them (``miou_valid_views``), else over all held-out views. Each row also carries what a
user sees (over Gaussians, see ``votesplat_ns/eval/ground_truth.py`` ``score_level``): the mean
per-object 3D completeness and purity, list precision, 3D AP@50, the numbers of objects and
instances, and the object-removal ghost percentage; the table means skip a value the scorer
left empty (None: e.g. no object matched).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import statistics
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from votesplat_ns.core.ply_io import atomic_write  # noqa: E402  (after the path set-up)

LEVELS = ("instance", "part")


def parse_variant(text: str) -> Tuple[str, Dict[str, object]]:
    """``name:key=value,key=value`` -> (name, {key: python literal or string})."""
    name, _, body = text.partition(":")
    if not name:
        raise argparse.ArgumentTypeError(f"variant {text!r} has no name; write name:key=value,...")
    settings: Dict[str, object] = {}
    for item in filter(None, body.split(",")):
        key, sep, raw = item.partition("=")
        if not sep:
            raise argparse.ArgumentTypeError(f"variant {text!r}: {item!r} is not key=value")
        try:
            settings[key.strip()] = ast.literal_eval(raw.strip())
        except (ValueError, SyntaxError):
            settings[key.strip()] = raw.strip()
    return name, settings


def split_overrides(settings: Dict[str, object]) -> Tuple[Dict[str, object], Dict[str, object]]:
    model = {k: v for k, v in settings.items() if not k.startswith("dm.")}
    datamanager = {k[3:]: v for k, v in settings.items() if k.startswith("dm.")}
    return model, datamanager


def score(metrics: dict, level: str) -> dict:
    entry = metrics["levels"][level]
    valid = entry.get("miou_valid_views")
    return {
        "miou": float(valid if valid is not None else entry["miou"]),
        "miou_all_views": float(entry["miou"]),
        "precision": float(entry.get("precision_valid_views", entry["precision"])),
        "recall": float(entry.get("recall_valid_views", entry["recall"])),
        "completeness": float(entry.get("completeness", float("nan"))),
        "num_pred": int(entry["num_predicted_instances"]),
        "num_gt": entry.get("num_gt_objects"),
        "completeness_object": entry.get("mean_completeness_3d"),
        "purity_object": entry.get("mean_purity_3d"),
        "list_precision": entry.get("list_precision"),
        "ap50_3d": entry.get("ap50_3d"),
        "ghost_percent": entry.get("ghost_percent"),
        "ghost_matched_percent": entry.get("ghost_matched_percent"),
    }


def _mean(group: Sequence[dict], key: str, digits: int = 3) -> str:
    """Mean of a column over a group, skipping rows without the value; "-" when none has it."""
    values = [float(r[key]) for r in group if r.get(key) is not None]
    return f"{statistics.mean(values):.{digits}f}" if values else "-"


def run_job(job: dict) -> List[dict]:
    """Train one run and score it with every clustering variant (runs inside a worker process)."""
    import torch

    from votesplat_ns.cli.evaluate_cli import evaluate_run
    from votesplat_ns.ns.method import train_in_process

    run_dir = Path(job["run_dir"])
    model, datamanager = split_overrides(job["train_settings"])
    device = "cuda" if torch.cuda.is_available() else "cpu"
    start = time.time()
    config = train_in_process(
        Path(job["scene"]),
        run_dir,
        job["steps"],
        job["vote_start"],
        device,
        "run",
        Path(job["mask_folder"]) if job["mask_folder"] else None,
        seed=job["seed"],
        datamanager_overrides=datamanager,
        num_downscales=0,
        **model,
    )
    train_seconds = time.time() - start
    rows = []
    for cluster_name, cluster_settings in job["cluster_variants"]:
        options = {k: v for k, v in cluster_settings.items() if not k.startswith("mc.")}
        check = {k[3:]: v for k, v in cluster_settings.items() if k.startswith("mc.")}
        mask_check = bool(options.pop("mask_check", True))
        # evaluate_run's own clustering arguments are passed as such, the rest to cluster_levels
        own = {k: options.pop(k) for k in ("min_cluster_size", "min_samples", "max_points") if k in options}
        result = evaluate_run(  # every level
            config,
            run_dir / f"eval_{cluster_name}",
            mask_check=mask_check,
            mask_check_options=check,
            cluster_options=options,
            **own,
        )
        for level in LEVELS:
            if level in result.metrics["levels"]:
                rows.append(
                    {
                        **job["labels"],
                        "cluster": cluster_name,
                        "level": level,
                        **score(result.metrics, level),
                        "train_seconds": train_seconds,
                        "config": str(config),
                    }
                )
    return rows


def noisy_masks(scene: Path, folder: Path) -> Path:
    """``--masks noisy``: the scene's GT masks with SAM-like errors (``SAM_LIKE_NOISE``: splits, merges, boundary
    jitter, drops) written to ``folder``, the training's folder mask source."""
    from votesplat_ns.eval.mask_noise import SAM_LIKE_NOISE, write_noisy_masks

    return write_noisy_masks(scene, folder, SAM_LIKE_NOISE, overwrite=True)


def table(rows: Sequence[dict]) -> str:
    """Mean over scenes (and seeds) of each (masks, train, cluster, level), with the worst scene."""
    groups: Dict[tuple, List[dict]] = {}
    for row in rows:
        if "error" not in row:
            groups.setdefault((row["masks"], row["train"], row["cluster"], row["level"]), []).append(row)
    header = [
        "masks",
        "train",
        "cluster",
        "level",
        "runs",
        "mIoU",
        "worst scene",
        "precision",
        "recall",
        "completeness",
        "#pred",
        "completeness/object",
        "purity/object",
        "list precision",
        "AP@50 3D",
        "ghost %",
        "ghost % of objects with an instance",
        "#objects",
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for key in sorted(groups):
        group = groups[key]
        worst = min(group, key=lambda r: r["miou"])
        cells = [
            f"{statistics.mean(r['miou'] for r in group):.3f}",
            f"{worst['miou']:.3f} ({worst['scene']})",
            f"{statistics.mean(r['precision'] for r in group):.3f}",
            f"{statistics.mean(r['recall'] for r in group):.3f}",
            f"{statistics.mean(r['completeness'] for r in group):.3f}",
            f"{statistics.mean(r['num_pred'] for r in group):.1f}",
            _mean(group, "completeness_object"),
            _mean(group, "purity_object"),
            _mean(group, "list_precision"),
            _mean(group, "ap50_3d"),
            _mean(group, "ghost_percent", 1),
            _mean(group, "ghost_matched_percent", 1),
            _mean(group, "num_gt", 1),
        ]
        lines.append("| " + " | ".join([*map(str, key), str(len(group)), *cells]) + " |")
    failed = [r for r in rows if "error" in r]
    lines += [f"\nfailed: {r['scene']} {r['masks']} {r['train']} seed {r['seed']}: {r['error']}" for r in failed]
    return "\n".join(lines)


def per_scene_table(rows: Sequence[dict]) -> str:
    header = ["scene", "masks", "train", "cluster", "level", "seed", "mIoU", "mIoU all views", "precision", "#pred"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in sorted(
        (r for r in rows if "error" not in r),
        key=lambda r: (r["scene"], r["masks"], r["train"], r["cluster"], r["level"], r["seed"]),
    ):
        lines.append(
            f"| {r['scene']} | {r['masks']} | {r['train']} | {r['cluster']} | {r['level']} | {r['seed']} | {r['miou']:.3f} | "
            f"{r['miou_all_views']:.3f} | {r['precision']:.3f} | {r['num_pred']} |"
        )
    return "\n".join(lines)


def write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "w") as handle:
        handle.write(text)


def parse_args(argv: Optional[List[str]] = None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", type=Path, default=None, help="votesplat synth scene folders")
    parser.add_argument(
        "--family",
        choices=["tuning", "tuning-extra", "test"],
        default=None,
        help="every scene of this family set instead",
    )
    parser.add_argument(
        "--family-dir", type=Path, default=None, help="where the set was written (default build/family_<set>)"
    )
    parser.add_argument("--masks", nargs="+", choices=["gt", "noisy"], default=["gt"])
    parser.add_argument("--train", nargs="+", type=parse_variant, default=[("default", {})])
    parser.add_argument("--cluster", nargs="+", type=parse_variant, default=[("default", {})])
    parser.add_argument("--seeds", nargs="+", type=int, default=[42])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--vote-start", type=int, default=500)
    parser.add_argument("--jobs", type=int, default=4, help="trainings at a time (each in its own process)")
    parser.add_argument("--work-dir", type=Path, default=Path("build/sweep"))
    parser.add_argument("--job", type=Path, default=None, help=argparse.SUPPRESS)  # worker mode: one job file
    parser.add_argument(
        "--summarize", nargs="+", type=Path, default=None, metavar="JSON", help="print the tables of sweep.json files"
    )
    args = parser.parse_args(argv)
    if args.job is not None or args.summarize:
        return args
    if args.family is not None:
        if args.scenes is not None:
            parser.error("pass either --scenes or --family, not both")
        from votesplat_ns.eval.synthetic.family import read_family_set

        try:
            name, args.scenes = read_family_set(args.family_dir or Path("build") / f"family_{args.family}")
        except ValueError as err:
            parser.error(str(err))
        if name != args.family:
            parser.error(f"{args.family_dir} holds the {name} set, not {args.family}")
    elif not args.scenes:
        parser.error("pass --scenes or --family")
    for scene in args.scenes:
        if not (scene / "transforms.json").is_file():
            parser.error(f"{scene} has no transforms.json; pass folders written by votesplat synth")
    return args


def main(argv: Optional[List[str]] = None) -> int:
    args = parse_args(argv)
    if args.job is not None:  # worker: one training and its scores
        job = json.loads(args.job.read_text())
        try:
            rows = run_job(job)
        except Exception as err:  # one failed run must not lose the others' rows
            rows = [{**job["labels"], "error": f"{type(err).__name__}: {err}"}]
        write_text(args.job.with_suffix(".rows.json"), json.dumps(rows, indent=1))
        return 0
    if args.summarize:
        rows = [row for path in args.summarize for row in json.loads(path.read_text())["rows"]]
        print(table(rows))
        return 0

    work = args.work_dir.resolve()
    jobs = []
    for scene in args.scenes:
        name = scene.resolve().name
        for masks in args.masks:
            folder = None
            if masks == "noisy":
                folder = noisy_masks(scene, work / name / "noisy_masks")
            for train_name, train_settings in args.train:
                for seed in args.seeds:
                    run_dir = work / name / f"{masks}_{train_name}_seed{seed}"
                    jobs.append(
                        {
                            "labels": {"scene": name, "masks": masks, "train": train_name, "seed": seed},
                            "scene": str(scene.resolve()),
                            "run_dir": str(run_dir),
                            "mask_folder": str(folder) if folder else None,
                            "seed": seed,
                            "steps": args.steps,
                            "vote_start": args.vote_start,
                            "train_settings": train_settings,
                            "cluster_variants": args.cluster,
                        }
                    )
    print(
        f"sweep: {len(jobs)} trainings, {len(args.cluster)} clustering variants each, {args.jobs} at a time", flush=True
    )

    def launch(job: dict) -> List[dict]:
        run_dir = Path(job["run_dir"])
        run_dir.mkdir(parents=True, exist_ok=True)
        job_file = run_dir / "job.json"
        job_file.write_text(json.dumps(job))
        with open(run_dir / "worker.log", "w") as log:
            subprocess.run(
                [sys.executable, __file__, "--job", str(job_file)], stdout=log, stderr=subprocess.STDOUT, check=False
            )
        rows_file = job_file.with_suffix(".rows.json")
        if not rows_file.is_file():
            return [{**job["labels"], "error": f"worker died; see {run_dir / 'worker.log'}"}]
        rows = json.loads(rows_file.read_text())
        print(f"done: {job['labels']}", flush=True)
        return rows

    settings = {
        k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if k not in ("job", "summarize")
    }
    settings["scenes"] = [str(s) for s in args.scenes]
    if "noisy" in args.masks:
        from votesplat_ns.eval.mask_noise import SAM_LIKE_NOISE

        settings["noise"] = dataclasses.asdict(SAM_LIKE_NOISE)
    rows: List[dict] = []
    lock = threading.Lock()
    header = f"steps {args.steps}, vote start {args.vote_start}"
    if args.family:
        header = f"family set {args.family} (no default may be tuned on the test set); " + header

    def finished(job_rows: List[dict]) -> None:
        # written after every run, so a call cut short by its time limit still reports what finished
        with lock:
            rows.extend(job_rows)
            write_text(
                work / "sweep.json", json.dumps({"settings": settings, "rows": rows}, indent=1, default=str) + "\n"
            )
            text = f"{header}\n\n{table(rows)}\n\nPer scene:\n\n{per_scene_table(rows)}\n"
            write_text(work / "sweep.md", text)

    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        for job_rows in pool.map(launch, jobs):
            finished(job_rows)
    print((work / "sweep.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
