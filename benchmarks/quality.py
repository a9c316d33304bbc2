"""Instance quality of VoteSplat on synthetic scenes: GT masks vs noisy (SAM-like) masks, and ablations.

    python benchmarks/quality.py --scenes votesplat_ns/data/demo build/scenes/forward --steps 800
    python benchmarks/quality.py --scenes build/scenes/forward --ablation --steps 800
    python benchmarks/quality.py --scenes build/scenes/forward --ablation --retrofit --base-steps 1500 \
        --steps 400 --seeds 0 1 2
    python benchmarks/quality.py --merge runs/*/quality.json      # one table (+ mean over scenes) of parallel runs

For every scene folder (written by ``votesplat synth``) and every mask kind in ``--masks``:

* ``gt``: train votesplat with the dataset's exact instance/part masks;
* ``noisy``: write the GT masks corrupted by ``MaskNoise`` (``--split-rate`` ...) into
  ``<work-dir>/<scene>/noisy_masks`` and train with ``mask_source=folder`` on them;

then score the run with ``votesplat eval`` (held-out views, every level of ``--levels``, by
default instance and part: mIoU, precision and recall at IoU 0.5; 3D per-Gaussian purity) and
print one markdown table with a row per scene, mask kind and level, and a mean row over the scenes.
mIoU, precision and recall are votesplat eval's ``*_valid_views`` scores (held-out views whose RGB
reconstruction did not fail) where it reports them, else its scores over all held-out views; the
"views" column says which (and how many views were valid).

A family set (``votesplat synth family-set``) is scored with ``benchmarks/sweep.py --family``,
which also compares training and clustering variants. ``--ablation`` trains the
paper's Table 3 variants on each scene with GT masks instead: the full model, no depth distortion
(``vote_distortion=none``), votes blended in 2D (``vote_blend_space=2d``) and alpha*T vote weights
(``vote_weighting=alpha_t``).

``--seeds 0 1 2`` repeats every run with each seed and adds a table of means and standard
deviations: on the forward-facing scene one run does not rank the ablation variants.
``--retrofit`` trains each scene's geometry once without votes (``--base-steps``) and then trains
only the offsets on that frozen scene for ``--steps`` steps per run (the retrofit / vote-only path,
affordable on CPU). The vote losses never move the geometry (``votes_move_geometry`` off), so this
keeps exactly what the variants change and removes the run-to-run noise of densification.

Training runs in this process on CUDA if present, else CPU (``num_downscales=0``: the scenes are
small). Results go to ``<work-dir>/quality.md`` and ``quality.json`` (atomic writes); every run
keeps its folder (config.yml, checkpoint, eval/) under ``<work-dir>``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from votesplat_ns.core.ply_io import atomic_write  # noqa: E402  (after the path set-up)
from votesplat_ns.eval.mask_noise import SAM_LIKE_NOISE  # noqa: E402

ABLATIONS: Dict[str, Dict[str, str]] = {
    "full": {},
    "no distortion": {"vote_distortion": "none"},
    "2D blending": {"vote_blend_space": "2d"},
    "alpha*T weights": {"vote_weighting": "alpha_t"},
}


def atomic_write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "w") as handle:
        handle.write(text)


def _count(value) -> str:
    return str(value) if isinstance(value, int) else f"{float(value):.1f}"


def markdown_table(rows: Sequence[dict], first_columns: Sequence[str]) -> str:
    header = list(first_columns) + [
        "level",
        "mIoU",
        "views",
        "mIoU all views",
        "precision",
        "recall",
        "purity",
        "#GT",
        "#pred",
        "Gaussians",
        "train time",
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row in rows:
        if "error" in row:
            lines.append(
                "| "
                + " | ".join(
                    [str(row.get(c, "")) for c in first_columns]
                    + [str(row.get("level", "")), f"failed: {row['error']}"]
                    + [""] * 9
                )
                + " |"
            )
            continue
        values = [str(row[c]) for c in first_columns] + [
            row["level"],
            f"{row['miou']:.3f}",
            row.get("miou_views", "all"),
            f"{row.get('miou_all_views', row['miou']):.3f}",
            f"{row['precision']:.3f}",
            f"{row['recall']:.3f}",
            f"{row['purity']:.3f}",
            _count(row["num_gt"]),
            _count(row["num_pred"]),
            _count(row["num_gaussians"]),
            f"{row['train_seconds'] / 60:.1f} min",
        ]
        lines.append("| " + " | ".join(values) + " |")
    return "\n".join(lines)


MEAN_METRICS = (
    "miou",
    "miou_all_views",
    "precision",
    "recall",
    "purity",
    "num_gt",
    "num_pred",
    "num_gaussians",
    "train_seconds",
)


def mean_rows(rows: Sequence[dict], first_columns: Sequence[str]) -> List[dict]:
    """One row per (mask kind or variant, level) with the mean over its scenes' rows; failed runs are left out
    and named in the scene column (a mean over fewer scenes than were run must not pass unnoticed)."""
    others = [c for c in first_columns if c not in ("scene", "seed")]
    groups: Dict[tuple, List[dict]] = {}
    failed: Dict[tuple, List[str]] = {}
    for row in rows:
        key = tuple(row.get(c) for c in others) + (row.get("level"),)
        if "error" in row:
            failed.setdefault(key, []).append(str(row.get("scene")))
        else:
            groups.setdefault(key, []).append(row)
    means = []
    for key, group in groups.items():
        label = f"mean of {len(group)}"
        if failed.get(key):
            label += f" ({len(failed[key])} failed: {', '.join(failed[key])})"
        row = {"scene": label, **dict(zip(others, key[:-1])), "level": key[-1], "seed": group[0].get("seed")}
        for metric in MEAN_METRICS:
            row[metric] = statistics.mean(
                float(r.get(metric, r["miou"] if metric == "miou_all_views" else 0.0)) for r in group
            )
        views = {str(r.get("miou_views", "all")).split()[0] for r in group}  # "valid 5/6" -> "valid"
        row["miou_views"] = views.pop() if len(views) == 1 else "mixed"
        means.append(row)
    return means


def result_table(rows: Sequence[dict], first_columns: Sequence[str]) -> str:
    """The per-run rows, then (with more than one scene) the mean over scenes per mask kind/variant and level."""
    table = markdown_table(rows, first_columns)
    if len({row.get("scene") for row in rows}) > 1:
        table += "\n\nMean over scenes:\n\n" + markdown_table(mean_rows(rows, first_columns), first_columns)
    return table


SUMMARY_METRICS = ("miou", "precision", "recall", "purity", "num_pred")


def summary_table(rows: Sequence[dict], first_columns: Sequence[str]) -> str:
    """Mean ± standard deviation over seeds of each (scene, variant/masks) group."""
    groups: Dict[tuple, List[dict]] = {}
    for row in rows:
        if "error" not in row:
            groups.setdefault(tuple(row[c] for c in first_columns) + (row.get("level", ""),), []).append(row)
    header = list(first_columns) + ["level", "runs", "mIoU", "precision", "recall", "purity", "#pred"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for key, group in groups.items():
        cells = []
        for metric in SUMMARY_METRICS:
            values = [float(row[metric]) for row in group]
            spread = statistics.stdev(values) if len(values) > 1 else 0.0
            cells.append(
                f"{statistics.mean(values):.3f} ± {spread:.3f}"
                if metric != "num_pred"
                else f"{statistics.mean(values):.1f} ± {spread:.1f}"
            )
        lines.append("| " + " | ".join([str(k) for k in key] + [str(len(group))] + cells) + " |")
    return "\n".join(lines)


def train_base_scene(scene: Path, args) -> Path:
    """The scene's geometry without votes (the retrofit source), trained once and reused."""
    from votesplat_ns.ns.method import train_in_process
    from votesplat_ns.ns.run import latest_checkpoint

    base_dir = args.work_dir / scene.resolve().name / f"base_{args.base_steps}"
    for config_path in sorted(base_dir.glob("*/votesplat/run/config.yml")):  # <experiment>/<method>/<timestamp>
        try:
            latest_checkpoint(config_path)
            return config_path
        except ValueError:  # an interrupted training: train again
            pass
    # vote start after the last step, vote losses off: plain splatfacto training (the vote cache is still built)
    return train_in_process(
        scene,
        base_dir,
        args.base_steps,
        args.base_steps + 1,
        args.device,
        "run",
        num_downscales=0,
        vote_loss_weight=0.0,
        distortion_loss_weight=0.0,
    )


def write_base_ply(base_config: Path) -> Path:
    """The base run's Gaussians as a standard 3DGS PLY beside its config (the retrofit-from-PLY source)."""
    from votesplat_ns.core.ply_io import write_gaussian_table
    from votesplat_ns.core.scene import VOTE_OFFSETS_KEY, VOTE_SUPPORT_KEY, TrainedScene
    from votesplat_ns.ns.run import SPLAT_PARAM_NAMES, latest_checkpoint, load_gaussians

    path = base_config.parent / "scene.ply"
    if not path.exists():
        names = SPLAT_PARAM_NAMES + (VOTE_OFFSETS_KEY, VOTE_SUPPORT_KEY)
        params = load_gaussians(latest_checkpoint(base_config), names)
        write_gaussian_table(path, TrainedScene.from_params(params).vertex_table())
    return path


def level_row(metrics: dict, level: str) -> dict:
    """The table's numbers for one level of a votesplat eval metrics.json: mIoU, precision and recall over the
    valid views where it reports them (``*_valid_views``), else over all held-out views."""
    if level not in metrics["levels"]:
        return {"level": level, "error": f"no {level!r} level scored (metrics.json has {sorted(metrics['levels'])})"}
    scores = metrics["levels"][level]
    valid = scores.get("miou_valid_views")

    def on_valid(key: str) -> float:
        value = scores.get(f"{key}_valid_views")
        return scores[key] if valid is None or value is None else value

    views = "all"
    if valid is not None:
        views = (
            f"valid {scores['num_valid_views']}/{len(metrics['view_names'])}"
            if "num_valid_views" in scores and "view_names" in metrics
            else "valid"
        )
    return {
        "level": level,
        "miou": on_valid("miou"),
        "miou_views": views,
        "miou_all_views": scores["miou"],
        "precision": on_valid("precision"),
        "recall": on_valid("recall"),
        "purity": scores["purity"],
        "completeness": scores["completeness"],
        "num_gt": scores["scores_2d"]["num_gt"],
        "num_pred": scores["num_predicted_instances"],
        "num_gaussians": metrics["num_gaussians"],
    }


def run_one(
    scene: Path, run_dir: Path, args, mask_folder: Optional[Path] = None, seed: int = 42, **overrides
) -> List[dict]:
    """Train once, score every level of ``args.levels``: one row per level."""
    from votesplat_ns.ns.evaluate import evaluate_run
    from votesplat_ns.ns.method import train_in_process

    start = time.time()
    config_path = train_in_process(
        scene,
        run_dir,
        args.steps,
        args.vote_start,
        args.device,
        "run",
        mask_folder,
        seed=seed,
        num_downscales=0,
        **overrides,
    )
    train_seconds = time.time() - start
    start = time.time()
    level = args.levels[0] if len(args.levels) == 1 else None  # None: every level the model and the GT share
    result = evaluate_run(config_path, run_dir / "eval", level=level, min_weight=args.min_weight)
    eval_seconds = time.time() - start
    common = {
        "seed": seed,
        "train_seconds": train_seconds,
        "eval_seconds": eval_seconds,
        "config": str(config_path),
        "metrics": str(result.output_dir / "metrics.json"),
        "summary": result.metrics["summary"],
    }
    return [{**common, **level_row(result.metrics, name)} for name in args.levels]


def parse_args(argv: Optional[List[str]] = None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--scenes", nargs="+", type=Path, default=None, help="scene folders (default: the bundled demo scene)"
    )
    parser.add_argument("--masks", nargs="+", choices=["gt", "noisy"], default=["gt", "noisy"])
    parser.add_argument(
        "--ablation", action="store_true", help="train the Table 3 variants (GT masks) instead of gt/noisy"
    )
    parser.add_argument(
        "--variants", nargs="+", choices=sorted(ABLATIONS), default=list(ABLATIONS), help="ablation variants to run"
    )
    parser.add_argument("--steps", type=int, default=800)
    parser.add_argument("--vote-start", type=int, default=100)
    parser.add_argument(
        "--vote-pixels",
        type=int,
        default=None,
        help="vote_pixels_per_step (model default 4096); fewer makes CPU steps cheaper",
    )
    parser.add_argument(
        "--vote-every", type=int, default=None, help="vote_every_n_steps (model default 4; a retrofit votes every step)"
    )
    parser.add_argument(
        "--distortion-weight",
        type=float,
        default=None,
        help="lambda_d, distortion_loss_weight (model default 0.1; configs/ presets: 360 0.1, forward-facing 1.0)",
    )
    parser.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto")
    parser.add_argument(
        "--levels",
        "--level",
        nargs="+",
        default=["instance", "part"],
        help="vote levels scored, a row each (metrics.json has every level)",
    )
    parser.add_argument("--min-weight", type=float, default=0.5)
    parser.add_argument("--work-dir", type=Path, default=Path("build/quality"))
    parser.add_argument("--split-rate", type=float, default=SAM_LIKE_NOISE.split_rate)
    parser.add_argument("--merge-rate", type=float, default=SAM_LIKE_NOISE.merge_rate)
    parser.add_argument("--jitter-rate", type=float, default=SAM_LIKE_NOISE.jitter_rate)
    parser.add_argument("--drop-rate", type=float, default=SAM_LIKE_NOISE.drop_rate)
    parser.add_argument("--noise-seed", type=int, default=0)
    parser.add_argument("--seeds", nargs="+", type=int, default=[42], help="repeat every run with each training seed")
    parser.add_argument(
        "--retrofit", action="store_true", help="train the offsets only, on a scene trained once without votes"
    )
    parser.add_argument("--base-steps", type=int, default=1500, help="training steps of that scene (with --retrofit)")
    parser.add_argument(
        "--retrofit-init",
        nargs="+",
        choices=["zero", "lifted"],
        default=["zero"],
        help="start of the offsets (with --retrofit), a run each: zero, or lifted mask centroids (retrofit_init)",
    )
    parser.add_argument(
        "--retrofit-source",
        nargs="+",
        choices=["checkpoint", "ply"],
        default=["checkpoint"],
        help="what a retrofit reads (with --retrofit), a run each: the base run's checkpoint, or its Gaussians "
        "written as a standard 3DGS PLY (the layout of ns-export gaussian-splat, in the same frame)",
    )
    parser.add_argument(
        "--summarize",
        nargs="+",
        type=Path,
        default=None,
        metavar="JSON",
        help="train nothing: print mean ± std over the rows of these quality.json/ablation.json files (runs made in parallel)",
    )
    parser.add_argument(
        "--merge",
        nargs="+",
        type=Path,
        default=None,
        metavar="JSON",
        help="train nothing: print one table of the rows of these quality.json files (one scene each, say) and the mean over scenes",
    )
    args = parser.parse_args(argv)
    if args.summarize or args.merge:
        return args
    if args.scenes is None:
        args.scenes = [Path(__file__).resolve().parents[1] / "votesplat_ns" / "data" / "demo"]
    if args.retrofit:
        args.vote_start = 0  # a retrofit votes from its first step
    if args.steps <= args.vote_start:
        parser.error(f"--steps ({args.steps}) must exceed --vote-start ({args.vote_start}) so the votes get trained")
    for scene in args.scenes:
        if not (scene / "transforms.json").is_file():
            parser.error(f"{scene} has no transforms.json; pass folders written by votesplat synth")
    return args


def merge(files: Sequence[Path]) -> str:
    """The rows of several quality.json files (runs made in parallel) as one table, with the mean over scenes."""
    rows, first_columns = _read_rows(files)
    if first_columns != ["scene", "masks"]:
        raise SystemExit("quality.py: error: --merge takes quality.json files; use --summarize for ablation.json")
    rows.sort(key=lambda r: (str(r.get("masks")), str(r.get("level")), str(r.get("scene"))))
    return result_table(rows, first_columns)


def summarize(files: Sequence[Path]) -> str:
    """One mean ± std table over the runs stored in several quality.json / ablation.json files."""
    rows, first_columns = _read_rows(files)
    return summary_table(rows, first_columns)


def _read_rows(files: Sequence[Path]):
    rows: List[dict] = []
    first_columns: Optional[List[str]] = None
    for path in files:
        try:
            stored = json.loads(Path(path).read_text())
        except (OSError, ValueError) as err:
            raise SystemExit(
                f"quality.py: error: cannot read {path} ({err}); pass quality.json/ablation.json files this script wrote"
            )
        columns = ["scene", "variant"] if stored["settings"].get("ablation") else ["scene", "masks"]
        if first_columns not in (None, columns):
            raise SystemExit(
                "quality.py: error: --summarize got both ablation and quality files; summarize each kind separately"
            )
        first_columns = columns
        rows.extend(stored["rows"])
    assert first_columns is not None
    return rows, first_columns


def main(argv: Optional[List[str]] = None) -> int:
    args = parse_args(argv)
    if args.summarize:
        print(summarize(args.summarize))
        return 0
    if args.merge:
        print(merge(args.merge))
        return 0
    import torch

    from votesplat_ns.eval.mask_noise import MaskNoise, write_noisy_masks

    if args.device == "auto":
        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    args.work_dir.mkdir(parents=True, exist_ok=True)
    rows: List[dict] = []
    first_columns = ["scene", "variant"] if args.ablation else ["scene", "masks"]
    if args.retrofit and (args.retrofit_init != ["zero"] or args.retrofit_source != ["checkpoint"]):
        first_columns += ["init", "source"]
    suffix = "ablation" if args.ablation else "quality"

    def record(row: dict) -> None:
        rows.append(row)
        table = result_table(rows, [*first_columns, "seed"] if len(args.seeds) > 1 else first_columns)
        settings = (
            f"steps {args.steps}, vote start {args.vote_start}, vote pixels per step {args.vote_pixels or 'default (4096)'}, "
            f"vote every {1 if args.retrofit else args.vote_every or 'default (4)'} steps, "
            f"lambda_d {args.distortion_weight if args.distortion_weight is not None else 'default (0.1)'}, "
            f"device {args.device}, levels {' '.join(args.levels)}; mIoU over the held-out views that votesplat eval "
            "counts as valid where it reports them (views column), else over all"
        )
        if args.retrofit:
            settings = f"retrofit on a scene trained {args.base_steps} steps without votes; " + settings
        if len(args.seeds) > 1:
            table += (
                "\n\nMean ± standard deviation over seeds "
                + ", ".join(map(str, args.seeds))
                + ":\n\n"
                + summary_table(rows, first_columns)
            )
        atomic_write_text(args.work_dir / f"{suffix}.md", f"{settings}\n\n{table}\n")
        atomic_write_text(
            args.work_dir / f"{suffix}.json",
            json.dumps(
                {
                    "settings": vars(args) | {"scenes": [str(s) for s in args.scenes], "work_dir": str(args.work_dir)},
                    "rows": rows,
                },
                indent=2,
                default=str,
            )
            + "\n",
        )
        print(table, flush=True)

    noise = MaskNoise(
        split_rate=args.split_rate,
        merge_rate=args.merge_rate,
        jitter_rate=args.jitter_rate,
        drop_rate=args.drop_rate,
        seed=args.noise_seed,
    )
    base = {} if args.vote_pixels is None else {"vote_pixels_per_step": args.vote_pixels}
    if args.vote_every is not None:
        base["vote_every_n_steps"] = args.vote_every
    if args.distortion_weight is not None:
        base["distortion_loss_weight"] = args.distortion_weight
    for scene in args.scenes:
        name = scene.resolve().name
        jobs = []
        if args.ablation:
            for variant in args.variants:
                jobs.append(
                    (
                        {"scene": name, "variant": variant},
                        args.work_dir / name / ("ablation_" + variant.replace(" ", "_").replace("*", "")),
                        None,
                        {**base, **ABLATIONS[variant]},
                    )
                )
        else:
            for masks in args.masks:
                folder = None
                if masks == "noisy":
                    folder = write_noisy_masks(scene, args.work_dir / name / "noisy_masks", noise, overwrite=True)
                jobs.append(({"scene": name, "masks": masks}, args.work_dir / name / masks, folder, dict(base)))
        if args.retrofit:
            base_config = train_base_scene(scene, args)
            sources = {"checkpoint": base_config}
            if "ply" in args.retrofit_source:
                sources["ply"] = write_base_ply(base_config)
            # the defaults keep the run folders and labels of earlier runs
            named = args.retrofit_init != ["zero"] or args.retrofit_source != ["checkpoint"]
            jobs = [
                (
                    {**labels, **({"init": init, "source": source} if named else {})},
                    run_dir.with_name(f"{run_dir.name}_{init}_{source}") if named else run_dir,
                    folder,
                    {**overrides, "retrofit_from": sources[source], "retrofit_init": init},
                )
                for labels, run_dir, folder, overrides in jobs
                for init in args.retrofit_init
                for source in args.retrofit_source
            ]
        for seed in args.seeds:
            for labels, run_dir, folder, overrides in jobs:
                if len(args.seeds) > 1:
                    run_dir = run_dir.with_name(f"{run_dir.name}_seed{seed}")
                try:
                    level_rows = run_one(scene, run_dir, args, folder, seed=seed, **overrides)
                except Exception as err:  # one failed run must not lose the others' rows
                    level_rows = [
                        {"error": f"{type(err).__name__}: {err}", "seed": seed, "level": level} for level in args.levels
                    ]
                for row in level_rows:
                    record({**labels, **row})
    print(f"\nwrote {args.work_dir / (suffix + '.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
