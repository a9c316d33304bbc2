"""Compares the step timings of two ``ns-train`` runs (``VOTESPLAT_STEP_TIMES=1``, run.sh).

For each run: the set-up before step 0, the sum of the step walls over step ranges, the tail after
the last step, and per phase the mean host time per step over each range; then the steps whose wall
exceeds ``--slow-ms``, grouped (first visits of views, JIT compiles and refinements show there).

    python benchmarks/step_times.py steps_fox_splatfacto.json steps_fox_votesplat.json --ranges 0:500 500:3000

``--vote-every N --vote-start S`` (a votesplat run with ``--pipeline.model.vote-every-n-steps N``) splits each
range into the steps that vote and those that do not, and prints per phase the difference of their means: with
N = 2 the two kinds alternate within one run, so their difference is a vote step's cost without the ±1 ms
that separate runs differ by (work a vote step leaves to the next step is counted in the other kind).
"""

from __future__ import annotations

import argparse
import json
import statistics
from typing import Dict, List, Tuple


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


def vote_step_cost(record: Dict, ranges: List[Tuple[int, int]], every: int, start: int) -> List[str]:
    """Per range: the mean and median wall of the vote steps and of the others, and per phase the difference of
    their means (vote steps minus the others)."""
    steps, walls = record["steps"], record["wall_ms"]
    lines = []
    for lo, hi in ranges:
        picked = [i for i, step in enumerate(steps) if lo <= step < hi]
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="steps_<experiment>_<method>.json files")
    parser.add_argument("--ranges", nargs="+", default=["0:500", "500:100000"], help="step ranges A:B")
    parser.add_argument("--slow-ms", type=float, default=60.0, help="list the steps slower than this")
    parser.add_argument("--vote-every", type=int, help="the run's vote_every_n_steps: split vote steps from others")
    parser.add_argument("--vote-start", type=int, default=500, help="the run's vote_start_step (with --vote-every)")
    args = parser.parse_args()
    for path in args.runs:
        with open(path) as handle:
            record = json.load(handle)
        print(path)
        print("\n".join(summarize(record, _ranges(args.ranges), args.slow_ms)))
        if args.vote_every:
            print("\n".join(vote_step_cost(record, _ranges(args.ranges), args.vote_every, args.vote_start)))


if __name__ == "__main__":
    main()
