"""Compares the step timings of two ``ns-train`` runs (``VOTESPLAT_STEP_TIMES=1``, run.sh).

For each run: the set-up before step 0, the sum of the step walls over step ranges, the tail after
the last step, and per phase the mean host time per step over each range; then the steps whose wall
exceeds ``--slow-ms``, grouped (first visits of views, JIT compiles and refinements show there).

    python benchmarks/step_times.py steps_fox_splatfacto.json steps_fox_votesplat.json --ranges 0:500 500:3000

``--vote-every N --vote-start S`` (a votesplat run with ``--pipeline.model.vote-every-n-steps N``) splits each
range into the steps that vote and those that do not, and prints per phase the difference of their means: with
N = 2 the two kinds alternate within one run, so their difference is a vote step's cost without the ±1 ms
that separate runs differ by (work a vote step leaves to the next step is counted in the other kind).

``--table DIR ...`` reads the run folders of ``run.sh train-balanced`` (each: one ``steps_*.json`` and its
``train_*.json``) and prints one row per run and the ratios of votesplat's means to splatfacto's over the runs
that finished (the stage alternates the methods, so a drift of the machine falls on both alike):

    python benchmarks/step_times.py --table 1-splatfacto 2-votesplat 3-votesplat 4-splatfacto --vote-start 500
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
from pathlib import Path
from typing import Dict, List, Optional, Tuple


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


def vote_step_cost(
    record: Dict, ranges: List[Tuple[int, int]], every: int, start: int, skip_refinement: bool = False
) -> List[str]:
    """Per range: the mean and median wall of the vote steps and of the others, and per phase the difference of
    their means (vote steps minus the others). ``skip_refinement`` leaves out every 100th step and the one after
    it (densification and the eval image, ~100 ms, land there: with an even ``every`` and ``start`` all on vote
    steps, which moves the means by a few tenths of a ms)."""
    steps, walls = record["steps"], record["wall_ms"]
    lines = []
    for lo, hi in ranges:
        picked = [i for i, step in enumerate(steps) if lo <= step < hi]
        if skip_refinement:
            picked = [i for i in picked if steps[i] % 100 not in (0, 1)]
        voting = [i for i in picked if steps[i] >= start and (steps[i] - start) % every == 0]
        vote_rows = set(voting)
        other = [i for i in picked if i not in vote_rows]
        if not voting or not other:
            continue

        def stats(rows: List[int], values: List[float]) -> Tuple[float, float]:
            return statistics.mean(values[i] for i in rows), statistics.median(values[i] for i in rows)

        (vote_mean, vote_median), (other_mean, other_median) = stats(voting, walls), stats(other, walls)
        lines.append(
            f"  steps [{lo}, {hi}): {len(voting)} vote steps, mean {vote_mean:.2f} / median {vote_median:.2f} ms; "
            f"{len(other)} others, mean {other_mean:.2f} / median {other_median:.2f} ms; "
            f"difference mean {vote_mean - other_mean:+.2f} / median {vote_median - other_median:+.2f} ms"
        )
        for label, values in sorted(record["phases_ms"].items()):
            difference = stats(voting, values)[0] - stats(other, values)[0]
            if abs(difference) >= 0.01:
                lines.append(f"      {label:<45} {difference:+7.3f} ms")
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
    parser.add_argument("--vote-every", type=int, help="the run's vote_every_n_steps: split vote steps from others")
    parser.add_argument("--vote-start", type=int, default=500, help="the runs' vote_start_step (--vote-every, --table)")
    parser.add_argument(
        "--skip-refinement", action="store_true", help="--vote-every: leave out every 100th step and the one after"
    )
    args = parser.parse_args(argv)
    if args.table:
        print("\n".join(balanced_table([Path(run) for run in args.runs], args.vote_start)))
        return
    for path in args.runs:
        with open(path) as handle:
            record = json.load(handle)
        print(path)
        print("\n".join(summarize(record, _ranges(args.ranges), args.slow_ms)))
        if args.vote_every:
            cost = vote_step_cost(record, _ranges(args.ranges), args.vote_every, args.vote_start, args.skip_refinement)
            print("\n".join(cost))


if __name__ == "__main__":
    main()
