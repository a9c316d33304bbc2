"""Compares the step timings of two ``ns-train`` runs (``VOTESPLAT_STEP_TIMES=1``, run.sh).

For each run: the set-up before step 0, the sum of the step walls over step ranges, the tail after
the last step, and per phase the mean host time per step over each range; then the steps whose wall
exceeds ``--slow-ms``, grouped (first visits of views, JIT compiles and refinements show there).

    python benchmarks/step_times.py steps_fox_splatfacto.json steps_fox_votesplat.json --ranges 0:500 500:3000
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="steps_<experiment>_<method>.json files")
    parser.add_argument("--ranges", nargs="+", default=["0:500", "500:100000"], help="step ranges A:B")
    parser.add_argument("--slow-ms", type=float, default=60.0, help="list the steps slower than this")
    args = parser.parse_args()
    for path in args.runs:
        with open(path) as handle:
            record = json.load(handle)
        print(path)
        print("\n".join(summarize(record, _ranges(args.ranges), args.slow_ms)))


if __name__ == "__main__":
    main()
