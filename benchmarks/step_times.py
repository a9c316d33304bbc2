"""Every step's wall time of ``ns-train`` runs: recorded in the run, compared afterwards.

Recording: ``scripts/gpu/run.sh``'s launcher calls ``install_step_times`` before nerfstudio's trainer starts when
``VOTESPLAT_STEP_TIMES`` is set (for either method, so splatfacto and votesplat are timed alike). For every step
it writes its wall time (from one step's start to the next one's), the set-up before step 0 and the tail after
the last step's iteration (the final callbacks, e.g. votesplat's foreground pass, and the checkpoint); with
``VOTESPLAT_STEP_TIMES=1`` also the host time of each phase of ``PHASES`` (``walls``: not the phases, whose
wrappers would charge votesplat's more numerous calls). The host and the GPU run in lock step in these
trainings (splatfacto reads the GPU ~15 times a step), so a phase's host time includes the GPU work it waits for.

Comparing two runs' files: for each, the set-up, the sum of the step walls over step ranges, the tail and per
phase the mean host time per step over each range; then the steps whose wall exceeds ``--slow-ms``, grouped
(first visits of views, JIT compiles and refinements show there):

    python benchmarks/step_times.py steps_fox_splatfacto.json steps_fox_votesplat.json --ranges 0:500 500:3000

``--table DIR ...`` reads the run folders of ``run.sh train-balanced`` (each: one ``steps_*.json`` and its
``train_*.json``) and prints one row per run and the ratios of votesplat's means to splatfacto's over the runs
that finished (the stage alternates the methods, so a drift of the machine falls on both alike):

    python benchmarks/step_times.py --table 1-splatfacto 2-votesplat 3-votesplat 4-splatfacto --vote-start 500
"""

from __future__ import annotations

import argparse
import atexit
import collections
import importlib
import json
import math
import statistics
import time
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

# ---------------------------------------------------------------------------- recording, in ns-train

# (module, class, method): the phases of a step, as nerfstudio 1.1.5 calls them
PHASES = (
    ("nerfstudio.engine.trainer", "Trainer", "train_iteration"),
    ("nerfstudio.pipelines.base_pipeline", "VanillaPipeline", "get_train_loss_dict"),
    ("nerfstudio.data.datamanagers.full_images_datamanager", "FullImageDatamanager", "next_train"),
    ("nerfstudio.models.splatfacto", "SplatfactoModel", "get_outputs"),
    ("nerfstudio.models.splatfacto", "SplatfactoModel", "get_loss_dict"),
    ("nerfstudio.models.splatfacto", "SplatfactoModel", "get_metrics_dict"),
    ("nerfstudio.models.splatfacto", "SplatfactoModel", "step_post_backward"),
    ("nerfstudio.engine.optimizers", "Optimizers", "optimizer_scaler_step_some"),
    ("nerfstudio.engine.optimizers", "Optimizers", "zero_grad_some"),
    ("torch.autograd", None, "backward"),
    ("nerfstudio.engine.optimizers", "Optimizers", "scheduler_step_all"),
    ("votesplat_ns.ns.datamanager", "VoteDataManager", "kept_vote_batch"),
    ("votesplat_ns.ns.model", "VoteSplatModel", "get_outputs"),
    ("votesplat_ns.ns.model", "VoteSplatModel", "get_metrics_dict"),
    ("votesplat_ns.ns.model", "VoteSplatModel", "get_loss_dict"),
    ("votesplat_ns.ns.model", "VoteSplatModel", "step_post_backward"),
    ("votesplat_ns.ns.model", "VoteSplatModel", "vote_loss_terms"),
    ("votesplat_ns.ns.model", "VoteSplatModel", "record_vote_support"),
    ("votesplat_ns.core.vote_fused", None, "vote_losses_tiled"),
    # the parts of a fused vote step (vote_loss_terms' remainder is the draw and the model's own code)
    ("votesplat_ns.ns.model", "VoteSplatModel", "_vote_maps"),
    ("votesplat_ns.ns.model", "VoteSplatModel", "_support_in_backward"),
    ("votesplat_ns.core.vote_fused", None, "vote_losses_sampled"),
    ("votesplat_ns.core.vote_fused", "_FusedVoteLosses", "forward"),
    ("votesplat_ns.core.vote_fused", "_FusedVoteLosses", "backward"),
    ("votesplat_ns.core.vote_kernel", None, "_launch"),
)


def _timed(function: Callable, label: str, totals: Dict[str, float]) -> Callable:
    def wrapped(*args, **kwargs):
        start = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            totals[label] = totals.get(label, 0.0) + time.perf_counter() - start

    wrapped.__wrapped__ = function  # type: ignore[attr-defined]
    return wrapped


def _install_phases(wrap: Callable[[Callable, str], Callable]) -> None:
    for module_name, class_name, name in PHASES:
        module = importlib.import_module(module_name)
        owner = getattr(module, class_name) if class_name else module
        label = f"{class_name or module_name.rsplit('.', 1)[-1]}.{name}"
        wrapped = wrap(getattr(owner, name), label)
        # an autograd Function's forward and backward are static methods: kept static
        static = class_name is not None and isinstance(vars(owner).get(name), staticmethod)
        setattr(owner, name, staticmethod(wrapped) if static else wrapped)
        if class_name is None:  # a module function: rebind it where the model imported it
            model = importlib.import_module("votesplat_ns.ns.model")
            if hasattr(model, name):
                setattr(model, name, getattr(owner, name))


def install_step_times(out_path: str, phases: bool = True) -> None:
    """Time every step of ns-train and its phases (host time, no profiler) into ``out_path`` (JSON). Without
    ``phases`` only the steps: the phases' wrappers cost each call a few microseconds, and votesplat has more of
    them (its vote losses' parts), which would charge a comparison of the methods' walls to votesplat."""
    from nerfstudio.engine.trainer import Trainer

    process_start = time.perf_counter()
    phase_totals: Dict[str, float] = {}
    if phases:
        _install_phases(lambda function, label: _timed(function, label, phase_totals))
    original = Trainer.train_iteration
    record: Dict = {"steps": [], "wall_ms": [], "phases_ms": collections.defaultdict(list)}
    state: Dict = {}

    def close_step(now: float) -> None:
        if "step" in state:
            record["steps"].append(state["step"])
            record["wall_ms"].append(round((now - state["start"]) * 1e3, 3))
            for label in phase_totals.keys() | record["phases_ms"].keys():
                values = record["phases_ms"][label]
                values.extend([0.0] * (len(record["steps"]) - 1 - len(values)))
                values.append(round(phase_totals.get(label, 0.0) * 1e3, 3))
        phase_totals.clear()

    def train_iteration(self, step):
        now = time.perf_counter()
        if "step" not in state:
            record["setup_s"] = round(now - process_start, 3)
        close_step(now)
        state.update(step=step, start=now)
        result = original(self, step)
        state["end"] = time.perf_counter()
        return result

    def write() -> None:
        now = time.perf_counter()
        if "end" in state:  # the last step ends with its iteration; what follows is the tail
            close_step(state["end"])
            record["tail_s"] = round(now - state["end"], 3)
        record["total_s"] = round(now - process_start, 3)
        record["phases_ms"] = dict(record["phases_ms"])
        with open(out_path, "w") as handle:
            json.dump(record, handle)

    Trainer.train_iteration = train_iteration
    atexit.register(write)


# ---------------------------------------------------------------------------- comparing


def _ranges(text: List[str]) -> List[Tuple[int, int]]:
    return [tuple(int(v) for v in item.split(":")) for item in text]  # type: ignore[misc]


def summarize(record: Dict, ranges: List[Tuple[int, int]], slow_ms: float) -> List[str]:
    steps, walls = record["steps"], record["wall_ms"]
    lines = [
        f"  set-up {record.get('setup_s', float('nan')):.2f} s, tail {record.get('tail_s', float('nan')):.2f} s, "
        f"total {record.get('total_s', float('nan')):.2f} s, steps {len(steps)}"
    ]
    for lo, hi in ranges:
        picked = [i for i, step in enumerate(steps) if lo <= step < hi]
        if not picked:
            continue
        wall = [walls[i] for i in picked]
        lines.append(
            f"  steps [{lo}, {hi}): sum {sum(wall) / 1e3:.2f} s, mean {statistics.mean(wall):.2f} ms, "
            f"median {statistics.median(wall):.2f} ms"
        )
        for label, values in sorted(record["phases_ms"].items()):
            mean = statistics.mean(values[i] for i in picked)
            if mean >= 0.05:
                lines.append(f"      {label:<45} mean {mean:7.3f} ms")
    slow = [(steps[i], walls[i]) for i in range(len(steps)) if walls[i] > slow_ms]
    lines.append(
        f"  steps over {slow_ms:g} ms: {len(slow)}, {sum(w for _, w in slow) / 1e3:.2f} s in all; "
        + ", ".join(f"{s}:{w:.0f}" for s, w in sorted(slow, key=lambda item: -item[1])[:25])
    )
    return lines


def run_row(folder: Path, vote_start: int) -> Optional[Dict]:
    """One run of ``run.sh train-balanced``: its method, walls, set-up, step 0, the step sums before and from
    ``vote_start`` and its eval PSNR; None when the folder holds no finished run (cut by the call's limit)."""
    steps_files, train_files = sorted(folder.glob("steps_*.json")), sorted(folder.glob("train_*.json"))
    if len(steps_files) != 1 or len(train_files) != 1:
        return None
    record = json.loads(steps_files[0].read_text())
    methods = json.loads(train_files[0].read_text()).get("methods", {})
    if len(methods) != 1:
        return None
    ((method, result),) = methods.items()
    if result.get("status") != "ok":
        return None
    walls = dict(zip(record["steps"], record["wall_ms"]))
    return {
        "run": folder.name,
        "method": method,
        "wall_s": result["wall_s"],
        "process_s": result.get("process", {}).get("wall_s", float("nan")),
        "setup_s": record["setup_s"],
        "step0_s": walls.get(0, float("nan")) / 1e3,
        "before_s": sum(ms for step, ms in walls.items() if 0 < step < vote_start) / 1e3,
        "from_s": sum(ms for step, ms in walls.items() if step >= vote_start) / 1e3,
        "from_steps": sum(1 for step in walls if step >= vote_start),
        "psnr": result.get("eval", {}).get("psnr", float("nan")),
    }


def balanced_table(folders: List[Path], vote_start: int) -> List[str]:
    """The runs' rows and votesplat's means over splatfacto's (run wall, process, the training loop after step 0),
    the mean difference of a step from ``vote_start`` on, and of the eval PSNR (without ns-eval: none)."""
    rows, lines = (
        [],
        [
            f"| run | method | run wall (process) | set-up | step 0 | steps 1–{vote_start - 1} | steps {vote_start}– | eval PSNR |",
            "|---|---|---|---|---|---|---|---|",
        ],
    )
    for folder in folders:
        row = run_row(folder, vote_start)
        if row is None:
            lines.append(f"| {folder.name} | | not finished | | | | | |")
            continue
        rows.append(row)
        lines.append(
            f"| {row['run']} | {row['method']} | {row['wall_s']:.1f} ({row['process_s']:.1f}) s | {row['setup_s']:.2f} s | "
            f"{row['step0_s']:.2f} s | {row['before_s']:.2f} s | {row['from_s']:.2f} s | "
            + ("—" if math.isnan(row["psnr"]) else f"{row['psnr']:.3f}")
            + " |"
        )
    by_method = {name: [row for row in rows if row["method"] == name] for name in ("splatfacto", "votesplat")}
    base, votes = by_method["splatfacto"], by_method["votesplat"]
    if not base or not votes:
        return lines + ["", "no ratio: a method has no finished run"]

    def ratio(key) -> float:  # of the means: the methods may have finished different numbers of runs
        return statistics.mean(key(row) for row in votes) / statistics.mean(key(row) for row in base)

    def per_step(group: List[Dict]) -> float:
        return sum(row["from_s"] for row in group) * 1e3 / max(1, sum(row["from_steps"] for row in group))

    psnr = statistics.mean(r["psnr"] for r in votes) - statistics.mean(r["psnr"] for r in base)
    lines += [
        "",
        f"votesplat / splatfacto ({len(votes)} and {len(base)} runs): run wall {ratio(lambda r: r['wall_s']):.3f}×, "
        f"process {ratio(lambda r: r['process_s']):.3f}×, steps 1– {ratio(lambda r: r['before_s'] + r['from_s']):.3f}×; "
        f"a step from {vote_start} on {per_step(votes) - per_step(base):+.2f} ms"
        + ("" if math.isnan(psnr) else f"; eval PSNR {psnr:+.3f} dB"),
        f"step 0 per run: {', '.join('%.2f' % row['step0_s'] for row in rows)} s (a first training of the machine "
        "takes ~4 s more: the stage's warm-up run is there to take it)",
    ]
    return lines


def main(argv: Optional[List[str]] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="steps_<experiment>_<method>.json files (with --table: run folders)")
    parser.add_argument("--table", action="store_true", help="the runs are run.sh train-balanced's run folders")
    parser.add_argument("--ranges", nargs="+", default=["0:500", "500:100000"], help="step ranges A:B")
    parser.add_argument("--slow-ms", type=float, default=60.0, help="list the steps slower than this")
    parser.add_argument("--vote-start", type=int, default=500, help="--table: the runs' vote_start_step")
    args = parser.parse_args(argv)
    if args.table:
        print("\n".join(balanced_table([Path(run) for run in args.runs], args.vote_start)))
        return
    for path in args.runs:
        with open(path) as handle:
            record = json.load(handle)
        print(path)
        print("\n".join(summarize(record, _ranges(args.ranges), args.slow_ms)))


if __name__ == "__main__":
    main()
