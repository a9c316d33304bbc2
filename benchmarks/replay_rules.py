"""Replay the mask check and its whole-object rules on dumped runs, on the CPU, scored as ``votesplat eval`` scores.

A rule's default is chosen by scoring the same trainings with and without it. ``benchmarks/sweep.py --cluster``
does that on the GPU; this does it on the CPU from a dump of each run, so that variants and the per-object detail
cost no GPU time (BENCHMARKS.md "Instances a user gets" chose the contact rule, the reach in the masks and the
views that show an instance this way):

    # where the runs were trained (after benchmarks/sweep.py): one .npz per run, from its sweep.json
    python benchmarks/replay_rules.py dump --sweep build/sweep/sweep.json --out build/dumps
    # anywhere: each variant against the defaults, per run and level
    python benchmarks/replay_rules.py replay build/dumps/*.npz --variant anyseen:unseen_min_seen=False
    # anywhere: the defaults with the check's masks made SAM-like noisy (the scene each run was trained on)
    python benchmarks/replay_rules.py noisy-evidence --pair build/dumps/<run>.npz build/family_test/family_2055

``dump`` runs ``votesplat eval``'s ``evaluate_run`` on each run (instances computed in memory; the run's kept
record is neither read nor written) and records, per level, what the mask check's rules were given (the vote
clustering's labels, the mask table, the votes, the options) and what the scorer was given (each Gaussian's GT
object, the held-out views' GT maps), plus the Gaussians the removal check renders and the scores eval gave. It
records them by wrapping ``regroup_with_masks`` and ``add_ghost_check`` as ``evaluate_run`` calls them; nothing
else changes. It also keeps the mask check's training views (cameras and mask labels per level), so that
:func:`retable` computes a level's table again on any machine, for variants of the evidence itself (its depth
tolerance, say) that the rules' keywords cannot reach. A dump of a 256x192 family run is 8-19 MB without the views.

``replay`` first replays the defaults and stops if they do not give the dumped instances and scores back. A
variant is ``name:key=value,...`` of ``regroup_with_masks`` keywords (those of
:func:`votesplat_ns.core.whole_objects.whole_objects` included: the sweep's ``mc.`` keys without ``mc.``). The
removal check (ghost %) runs at the instance level, and only where the variant changed the instances; it takes
about two minutes per run on two CPU cores.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from sweep import noisy_masks, parse_variant  # noqa: E402  (benchmarks/ is no package)

SCORES = ("num_predicted", "list_precision", "mean_completeness_3d", "mean_purity_3d", "ap50_3d", "ghost_percent")


# ------------------------------------------------------------------------------------------------ dump
def dump_run(config: Path, out: Path) -> Path:
    """Run ``evaluate_run`` on ``config`` and write what the rules and the scorer were given to ``out`` (.npz)."""
    from votesplat_ns.ns import evaluate, mask_views

    record: Dict[str, np.ndarray] = {}
    regroup, ghost, instances = mask_views.regroup_with_masks, evaluate.add_ghost_check, evaluate.run_instances
    view_masks = mask_views._view_masks
    train_views: Dict[int, tuple] = {}  # the mask check's views: index -> (view, masks per level)

    def recording_view_masks(datamanager, known, level_names, index, view):
        masks = view_masks(datamanager, known, level_names, index, view)
        train_views[index] = (view, [masks[name] for name in level_names])
        return masks

    def recording_regroup(ids, means, table, votes=None, **options):
        level = sum(key.startswith("ids_in_") for key in record)
        out_ids, stats = regroup(ids, means, table, votes=votes, **options)
        record.update(
            {
                f"ids_in_{level}": np.asarray(ids, np.int32),
                f"table_{level}": np.asarray(table),
                f"votes_{level}": np.asarray(votes, np.float32),
                f"ids_out_{level}": np.asarray(out_ids, np.int32),
                f"options_{level}": np.array(json.dumps(options, default=str)),
                "means": np.asarray(means, np.float32),
            }
        )
        return out_ids, stats

    def recording_ghost(result, scene, gt_labels, pred_ids, views, gt_maps, rasterize_fn):
        level = sum(key.startswith("gt_labels_") for key in record)
        if "keep" not in record:
            keep = scene.finite()
            gaussians = scene.gaussians(keep)[:4]
            record.update(
                {name: t.cpu().numpy() for name, t in zip(("g_means", "quats", "scales", "opacities"), gaussians)}
            )
            record["keep"] = keep
            record["viewmats"] = np.stack([v.viewmat.cpu().numpy() for v in views]).astype(np.float32)
            record["Ks"] = np.stack([v.K.cpu().numpy() for v in views]).astype(np.float32)
            record["sizes"] = np.array([(v.width, v.height) for v in views])
        record[f"gt_labels_{level}"] = np.asarray(gt_labels, np.int32)
        record[f"gt_maps_{level}"] = np.stack([np.asarray(m) for m in gt_maps]).astype(np.int32)
        ghost(result, scene, gt_labels, pred_ids, views, gt_maps, rasterize_fn)
        record[f"scores_{level}"] = np.array(json.dumps({key: result.get(key) for key in SCORES}))

    mask_views.regroup_with_masks, evaluate.add_ghost_check = recording_regroup, recording_ghost
    mask_views._view_masks = recording_view_masks
    evaluate.run_instances = lambda scene, run_dir, *args, **kwargs: instances(scene, None, *args, **kwargs)
    try:
        with tempfile.TemporaryDirectory() as scratch:
            evaluate.evaluate_run(config, scratch, log=None)
    finally:
        mask_views.regroup_with_masks, evaluate.add_ghost_check, evaluate.run_instances = regroup, ghost, instances
        mask_views._view_masks = view_masks
    if train_views:
        views, masks = zip(*(train_views[index] for index in sorted(train_views)))
        record.update(_views_record(views, list(zip(*masks))))
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, **record)
    return out


# ---------------------------------------------------------------------------------------------- replay
def load(path: Path) -> Dict[str, np.ndarray]:
    with np.load(path) as data:
        return {key: data[key] for key in data.files}


def levels_of(dump: Dict[str, np.ndarray]) -> List[int]:
    return sorted(int(key.rsplit("_", 1)[1]) for key in dump if key.startswith("scores_"))


def rules(dump: Dict[str, np.ndarray], level: int, **options) -> Tuple[np.ndarray, dict]:
    """The mask check and its rules on a dumped level, with the dumped options updated by ``options``."""
    from votesplat_ns.core.mask_consensus import regroup_with_masks

    settings = {**json.loads(str(dump[f"options_{level}"])), **options}
    votes = dump[f"votes_{level}"].astype(np.float64)
    labels = dump[f"ids_in_{level}"].astype(np.int64)
    return regroup_with_masks(labels, dump["means"].astype(np.float64), dump[f"table_{level}"], votes=votes, **settings)


def score(dump: Dict[str, np.ndarray], level: int, ids: np.ndarray, confidence, ghost: bool) -> dict:
    """The 3D scores of ``score_level`` (its 2D scores need renders and are left out) and, with ``ghost``, the
    removal check, as ``votesplat eval`` computes them."""
    import torch

    from votesplat_ns.core.cameras import PinholeView
    from votesplat_ns.eval.ground_truth import score_level
    from votesplat_ns.ns.evaluate import add_ghost_check_on
    from votesplat_ns.ns.rasterizer import rasterize

    gt_maps = list(dump[f"gt_maps_{level}"])
    gt = dump[f"gt_labels_{level}"]
    # the GT maps stand in for the rendered ones: the 3D scores read the per-Gaussian ids only
    result = score_level(gt_maps, [m - 1 for m in gt_maps], gt, ids, None, 0.5, confidence=confidence)
    out = {key: result.get(key) for key in SCORES if key != "ghost_percent"}
    if ghost:
        views = [
            PinholeView(torch.tensor(v), torch.tensor(k), int(size[0]), int(size[1]))
            for v, k, size in zip(dump["viewmats"], dump["Ks"], dump["sizes"])
        ]
        gaussians = [torch.as_tensor(dump[name]) for name in ("g_means", "quats", "scales", "opacities")]
        add_ghost_check_on(result, gaussians, dump["keep"], gt, ids, views, gt_maps, rasterize)
        out["ghost_percent"] = result["ghost_percent"]
    return out


def moved_gaussians(before: np.ndarray, after: np.ndarray) -> int:
    """How many Gaussians changed instance between two labelings of one level (-1: background), whatever the
    instances' numbers: the rules renumber instances by size, so a Gaussian added to one instance can swap two
    instances' ids. Instances are paired one to one by their shared Gaussians (background with background), and a
    Gaussian counts when its instance's pair does not hold it."""
    from scipy.optimize import linear_sum_assignment

    rows, row_of = np.unique(before, return_inverse=True)
    cols, col_of = np.unique(after, return_inverse=True)
    shared = np.zeros((rows.size, cols.size), dtype=np.int64)
    np.add.at(shared, (row_of.ravel(), col_of.ravel()), 1)
    weight = shared.astype(np.float64)
    both = (rows[:, None] < 0) & (cols[None, :] < 0)
    weight[(rows[:, None] < 0) ^ (cols[None, :] < 0)] = 0  # background pairs with background only
    weight[both] += before.size + 1  # and always does, where both have some
    r, c = linear_sum_assignment(weight, maximize=True)
    kept = sum(int(shared[i, j]) for i, j in zip(r, c) if (rows[i] < 0) == (cols[j] < 0))
    return int(before.size - kept)


def retable(dump: Dict[str, np.ndarray], level: int, depth_tolerance: Optional[float] = None) -> np.ndarray:
    """The level's mask table [V, N] computed again from the dump's training views (the mask check's cameras and
    masks) and Gaussians, as the check computes it (``centre`` evidence), on this machine's rasterizer: what a
    variant of the evidence (``depth_tolerance``, default the check's) would have given the rules."""
    import torch

    from votesplat_ns.core.cameras import PinholeView
    from votesplat_ns.core.mask_consensus import DEFAULT_DEPTH_TOLERANCE, fill_seen_masks, seen_pixels
    from votesplat_ns.ns.rasterizer import rasterize

    if "train_viewmats" not in dump:
        raise SystemExit("this dump holds no training views (dumped before they were recorded); dump the run again")
    tolerance = DEFAULT_DEPTH_TOLERANCE if depth_tolerance is None else depth_tolerance
    gaussians = [torch.as_tensor(dump[name]) for name in ("g_means", "quats", "scales", "opacities")]
    columns = np.flatnonzero(dump["keep"])
    masks = dump[f"train_masks_{level}"]
    table = np.full((len(masks), dump["keep"].shape[0]), -1, dtype=dump[f"table_{level}"].dtype)
    for v, (viewmat, K, size) in enumerate(zip(dump["train_viewmats"], dump["train_Ks"], dump["train_sizes"])):
        view = PinholeView(torch.tensor(viewmat), torch.tensor(K), int(size[0]), int(size[1]))
        fill_seen_masks(table[v], seen_pixels(rasterize, *gaussians, view, tolerance), masks[v], columns)
    return table


def training_views(scene: Path, work: Path, mask_folder: Optional[Path] = None) -> Dict[str, np.ndarray]:
    """The mask check's training views of a run trained on ``scene`` with votesplat's defaults, rebuilt on the CPU
    without its checkpoint (the cameras in the trained frame, the masks per level: the dataset's, or
    ``mask_folder``'s), under the keys a dump records them; the set-up's files go to ``work``."""
    from votesplat_ns.ns import mask_views
    from votesplat_ns.ns.method import setup_trainer_in_process

    pipeline = setup_trainer_in_process(scene, work, 1, 0, "cpu", mask_folder=mask_folder).pipeline
    levels = list(pipeline.datamanager.vote_levels)
    views, masks = mask_views.training_mask_views(pipeline, levels)
    return _views_record(views, [masks[name] for name in levels])


def _views_record(views: Sequence, masks_per_level: Sequence[Sequence[np.ndarray]]) -> Dict[str, np.ndarray]:
    """Training views [V] (PinholeView) and, per level, their mask labels [V] under the keys of a dump."""
    record = {
        "train_viewmats": np.stack([v.viewmat.cpu().numpy() for v in views]).astype(np.float32),
        "train_Ks": np.stack([v.K.cpu().numpy() for v in views]).astype(np.float32),
        "train_sizes": np.array([(v.width, v.height) for v in views]),
    }
    for level, masks in enumerate(masks_per_level):
        record[f"train_masks_{level}"] = np.stack(masks).astype(np.int32)
    return record


def noisy_evidence(path: Path, scene: Path, level: int = 0) -> str:
    """A table row: the dumped run's rules and scores with the check's table from its training masks → from the same
    views' masks with ``SAM_LIKE_NOISE``. The vote clustering stays the dumped training's: this measures what mask
    errors do to the check and the whole-object rules, not a training on noisy masks."""
    dump = load(path)
    with tempfile.TemporaryDirectory() as scratch:
        if "train_viewmats" not in dump:  # dumped before the views were recorded
            dump.update(training_views(scene, Path(scratch) / "masks"))
        folder = noisy_masks(scene, Path(scratch) / "noisy_masks")  # the sweeps' --masks noisy
        noisy = training_views(scene, Path(scratch) / "noisy", folder)
    if not np.array_equal(noisy["train_viewmats"], dump["train_viewmats"]):
        raise SystemExit(
            f"{path}: the scene's training views are not the dumped run's; pass the scene it was trained on"
        )
    changed = float((noisy[f"train_masks_{level}"] != dump[f"train_masks_{level}"]).mean())
    ids, stats = rules(dump, level)
    before = score(dump, level, ids, stats.get("confidence"), ghost=True)
    dump[f"train_masks_{level}"] = noisy[f"train_masks_{level}"]
    dump[f"table_{level}"] = retable(dump, level)
    noisy_ids, noisy_stats = rules(dump, level)
    after = score(dump, level, noisy_ids, noisy_stats.get("confidence"), ghost=True)
    cells = [_cell(before[key], after[key]) for key in SCORES]
    return f"| {path.stem} | {level} | {100 * changed:.1f} | " + " | ".join(cells) + " |"


def _cell(before, after) -> str:
    fmt = lambda v: "-" if v is None else (str(v) if isinstance(v, (int, str)) else f"{v:.3f}")  # noqa: E731
    return fmt(before) if before == after else f"{fmt(before)} → {fmt(after)}"


def replay(paths: List[Path], variants: List[Tuple[str, dict]]) -> str:
    """One table row per (run, level, variant): the defaults' scores → the variant's."""
    lines = [
        "| run | level | variant | Gaussians moved | " + " | ".join(SCORES) + " |",
        "|" + "---|" * (4 + len(SCORES)),
    ]
    for path in paths:
        dump = load(path)
        if not levels_of(dump):
            raise SystemExit(f"{path}: holds no scored level (dumped by an older tool); dump the run again")
        for level in levels_of(dump):
            ids, stats = rules(dump, level)
            dumped = json.loads(str(dump[f"scores_{level}"]))
            base = score(dump, level, ids, stats.get("confidence"), ghost=False)
            base["ghost_percent"] = dumped.get("ghost_percent")
            if not np.array_equal(ids, dump[f"ids_out_{level}"]) or any(
                base[key] != dumped.get(key) for key in SCORES if key != "ghost_percent"
            ):
                raise SystemExit(f"{path}: the defaults do not give the dumped level {level} back; dump it again")
            for name, options in variants:
                changed, changed_stats = rules(dump, level, **options)
                moved = moved_gaussians(ids, changed)
                after = dict(base)
                if moved:
                    after = score(dump, level, changed, changed_stats.get("confidence"), ghost=level == 0)
                    if level != 0:
                        after["ghost_percent"] = "not checked"
                cells = [_cell(base[key], after[key]) for key in SCORES]
                lines.append(f"| {path.stem} | {level} | {name} | {moved} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    dump = commands.add_parser("dump", help="dump trained runs (their config.yml, or the runs of a sweep.json)")
    dump.add_argument("--config", nargs="*", type=Path, default=[], help="config.yml of runs to dump")
    dump.add_argument("--sweep", nargs="*", type=Path, default=[], help="sweep.json files: their default-variant runs")
    dump.add_argument("--out", type=Path, required=True, help="folder for the .npz files")
    again = commands.add_parser("replay", help="score variants of the rules on dumps against the defaults")
    again.add_argument("dumps", nargs="+", type=Path)
    again.add_argument("--variant", nargs="+", type=parse_variant, required=True, help="name:key=value,...")
    noisy = commands.add_parser(
        "noisy-evidence", help="score dumped runs with their check's masks made SAM-like noisy (the scene is needed)"
    )
    noisy.add_argument("--pair", nargs=2, action="append", required=True, metavar=("DUMP", "SCENE"), type=Path)
    args = parser.parse_args(argv)
    if args.command == "noisy-evidence":
        header = "| run | level | mask pixels changed % | " + " | ".join(SCORES) + " |"
        print("\n".join([header, "|" + "---|" * (3 + len(SCORES))] + [noisy_evidence(d, s) for d, s in args.pair]))
        return 0
    if args.command == "dump":
        runs = [(config, config.parent.name) for config in args.config]
        for sweep in args.sweep:
            for row in json.loads(sweep.read_text())["rows"]:
                if row.get("cluster") == "default" and row.get("level") == "instance" and "error" not in row:
                    runs.append((Path(row["config"]), f"{row['scene']}_{row['masks']}_{row['seed']}"))
        if not runs:
            parser.error("no run to dump: pass --config or --sweep")
        for config, name in runs:
            written = dump_run(config, args.out / f"{name}.npz")
            print(f"{written}: {written.stat().st_size / 1e6:.1f} MB", flush=True)
        return 0
    print(replay(args.dumps, args.variant))
    return 0


if __name__ == "__main__":
    sys.exit(main())
