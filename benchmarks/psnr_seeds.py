"""Eval PSNR of trainings run side by side, each against its group's first, over the groups (seeds).

Two runs of one method and seed differ on the GPU by 0.3 to 3.7 dB (gsplat's backward adds with atomics and
densification amplifies the difference; BENCHMARKS.md, "Eval PSNR"), so one pair of runs cannot show a
0.1 dB difference. This reads the group folders of ``scripts/gpu/train_side_by_side.sh`` (``g<i>-seed<N>``,
each holding one folder ``<k>_<training>`` per training with that run's ``train_<stage>.json``) and prints,
per group, every training's PSNR and its difference to the group's first training (splatfacto, by default);
then, per training, the mean difference over the groups where both finished, its standard deviation and
standard error:

    python benchmarks/psnr_seeds.py /tmp/train_side_by_side/g*-seed* --json psnr_fox.json

A device call fits 10-20 seeds; ``--pool`` takes the JSONs of several calls (written by ``--json``) and gives the
same table over all their groups:

    python benchmarks/psnr_seeds.py --pool call1/psnr_side_fox.json call2/psnr_side_fox.json
"""

from __future__ import annotations

import argparse
import json
import math
import re
import statistics
from pathlib import Path
from typing import Dict, List, Optional, Tuple

GROUP_NAME = re.compile(r"^g(?P<group>\d+)-seed(?P<seed>\d+)$")
TRAINING_NAME = re.compile(r"^(?P<k>\d+)_(?P<training>\w+)$")


def read_psnr(folder: Path) -> Tuple[Optional[float], str]:
    """(eval PSNR, "ok") of one training's folder, or (None, why not) when it did not both train and evaluate."""
    for path in folder.glob("train_*.json"):
        for entry in json.loads(path.read_text()).get("methods", {}).values():
            if entry.get("status") == "ok" and entry.get("eval_status") == "ok":
                return (entry.get("eval") or {}).get("psnr"), "ok"
            return None, f"training {entry.get('status')}, eval {entry.get('eval_status')}"
    return None, f"no train_*.json (see {folder}/run.log)"


def read_groups(folders: List[Path]) -> List[Dict]:
    """[{"group", "seed", "trainings": {"<k>_<training>": PSNR or None}, "unfinished": {"<k>_<training>": why}}],
    in the groups' order."""
    groups = []
    for folder in folders:
        match = GROUP_NAME.match(folder.name)
        if not match:
            raise SystemExit(
                f"psnr_seeds.py: error: {folder} is not a group folder g<i>-seed<N> of train_side_by_side.sh"
            )
        runs = {int(m["k"]): p for p in folder.iterdir() if p.is_dir() and (m := TRAINING_NAME.match(p.name))}
        read = {runs[k].name: read_psnr(runs[k]) for k in sorted(runs)}
        groups.append(
            {
                "group": int(match["group"]),
                "seed": int(match["seed"]),
                "trainings": {label: psnr for label, (psnr, _) in read.items()},
                "unfinished": {label: why for label, (psnr, why) in read.items() if psnr is None},
            }
        )
    return sorted(groups, key=lambda g: g["group"])


def pool_groups(paths: List[Path]) -> List[Dict]:
    """The groups of several ``--json`` files, one after the other, numbered anew; each keeps its seed and the
    file it came from."""
    groups = []
    for path in paths:
        try:
            read = json.loads(path.read_text())["groups"]
        except (OSError, ValueError, KeyError, TypeError) as error:
            raise SystemExit(f"psnr_seeds.py: error: {path} is not a JSON written by psnr_seeds.py --json ({error})")
        for group in read:
            groups.append({**group, "group": len(groups) + 1, "source": str(path)})
    return groups


def summarize(groups: List[Dict]) -> Dict:
    """Per training after the groups' first (the baseline): the mean of its differences to the baseline over the
    groups where both have a PSNR, the differences' standard deviation and standard error."""
    labels: List[str] = []
    for group in groups:
        labels += [label for label in group["trainings"] if label not in labels]
    if not labels:
        return {"baseline": None, "groups": groups, "trainings": {}}
    baseline = labels[0]
    trainings = {}
    for label in labels[1:]:
        differences = []
        for group in groups:
            a, b = group["trainings"].get(label), group["trainings"].get(baseline)
            if a is not None and b is not None:
                differences.append(a - b)
        entry: Dict = {"paired_groups": len(differences)}
        if differences:
            entry["difference_mean"] = statistics.mean(differences)
        if len(differences) > 1:
            entry["difference_std"] = statistics.stdev(differences)
            entry["difference_standard_error"] = entry["difference_std"] / math.sqrt(len(differences))
        trainings[label] = entry
    return {"baseline": baseline, "groups": groups, "trainings": trainings}


def table(summary: Dict) -> str:
    baseline = summary["baseline"]
    if baseline is None:
        return "no trainings found"
    labels = [baseline, *summary["trainings"]]

    def cell(value: Optional[float], signed: bool = False) -> str:
        return "—" if value is None else (f"{value:+.3f}" if signed else f"{value:.3f}")

    lines = [
        "| group (seed) | "
        + " | ".join(f"{label} PSNR" for label in labels)
        + "".join(f" | {label} − {baseline}" for label in labels[1:])
        + " |",
        "|---" * (len(labels) * 2) + "|",
    ]
    for group in summary["groups"]:
        values = [group["trainings"].get(label) for label in labels]
        differences = [None if a is None or values[0] is None else a - values[0] for a in values[1:]]
        lines.append(
            f"| {group['group']} ({group['seed']}) | "
            + " | ".join(cell(v) for v in values)
            + "".join(f" | {cell(d, True)}" for d in differences)
            + " |"
        )
    for group in summary["groups"]:
        for label, why in group.get("unfinished", {}).items():
            lines.append(f"group {group['group']} ({group['seed']}), {label}: no PSNR: {why}")
    for label, entry in summary["trainings"].items():
        if not entry["paired_groups"]:
            lines.append(f"{label} − {baseline}: no group where both finished")
            continue
        spread = ""
        if "difference_standard_error" in entry:
            spread = f", std {entry['difference_std']:.3f}, standard error {entry['difference_standard_error']:.3f}"
        lines.append(
            f"{label} − {baseline}: mean **{entry['difference_mean']:+.3f} dB** over {entry['paired_groups']} group{'s' if entry['paired_groups'] != 1 else ''}{spread}"
        )
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("groups", nargs="*", type=Path, help="group folders g<i>-seed<N> of train_side_by_side.sh")
    parser.add_argument("--pool", nargs="+", type=Path, default=None, help="instead, --json files of several calls")
    parser.add_argument("--json", type=Path, default=None, help="also write the groups and means here")
    args = parser.parse_args(argv)
    if bool(args.groups) == bool(args.pool):
        parser.error("pass either group folders or --pool FILE...")
    summary = summarize(pool_groups(args.pool) if args.pool else read_groups(args.groups))
    print(table(summary))
    if args.json is not None:
        args.json.write_text(json.dumps(summary, indent=2) + "\n")


if __name__ == "__main__":
    main()
