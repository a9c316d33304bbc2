"""benchmarks/quality.py's tables: per-seed rows grouped into mean ± std, and the --summarize merge."""

from __future__ import annotations

import importlib.util
import json
import statistics
import sys
from pathlib import Path

import pytest

QUALITY_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "quality.py"


@pytest.fixture(scope="module")
def quality():
    spec = importlib.util.spec_from_file_location("votesplat_quality_benchmark", QUALITY_PATH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def row(variant, seed, miou, num_pred=5):
    return {"scene": "forward", "variant": variant, "seed": seed, "level": "instance", "miou": miou, "precision": 1.0,
            "recall": 0.5 + seed / 10, "purity": 0.9, "num_gt": 5, "num_pred": num_pred, "num_gaussians": 100,
            "train_seconds": 60.0}


def parse_summary(table: str):
    lines = [line for line in table.splitlines() if line.startswith("|")]
    header = [cell.strip() for cell in lines[0].strip("|").split("|")]
    return [dict(zip(header, (cell.strip() for cell in line.strip("|").split("|")))) for line in lines[2:]]


def test_summary_groups_seeds_and_skips_failed_runs(quality):
    rows = [row("full", 0, 0.8), row("full", 1, 0.9), row("full", 2, 1.0, num_pred=8),
            row("no distortion", 0, 0.7), {"scene": "forward", "variant": "no distortion", "seed": 1, "error": "RuntimeError: x"}]
    summary = {entry["variant"]: entry for entry in parse_summary(quality.summary_table(rows, ["scene", "variant"]))}
    assert summary["full"]["runs"] == "3" and summary["no distortion"]["runs"] == "1"
    assert summary["full"]["mIoU"] == f"{0.9:.3f} ± {statistics.stdev([0.8, 0.9, 1.0]):.3f}"
    assert summary["full"]["recall"] == f"{0.6:.3f} ± {statistics.stdev([0.5, 0.6, 0.7]):.3f}"
    assert summary["full"]["#pred"] == f"{6.0:.1f} ± {statistics.stdev([5, 5, 8]):.1f}"
    assert summary["no distortion"]["mIoU"] == "0.700 ± 0.000"  # one run: no spread to report


def test_summarize_merges_files_of_parallel_runs(quality, tmp_path):
    files = []
    for seed, miou in enumerate([0.6, 0.8]):
        path = tmp_path / f"seed{seed}" / "ablation.json"
        path.parent.mkdir()
        path.write_text(json.dumps({"settings": {"ablation": True}, "rows": [row("full", seed, miou)]}))
        files.append(path)
    (entry,) = parse_summary(quality.summarize(files))
    assert entry["runs"] == "2" and entry["mIoU"] == f"{0.7:.3f} ± {statistics.stdev([0.6, 0.8]):.3f}"
    assert quality.main(["--summarize", *map(str, files)]) == 0


def test_summarize_refuses_unreadable_or_mixed_files(quality, tmp_path):
    broken = tmp_path / "ablation.json"
    broken.write_text("{not json")
    with pytest.raises(SystemExit, match="cannot read"):
        quality.summarize([broken])
    ablation, masks = tmp_path / "a.json", tmp_path / "q.json"
    ablation.write_text(json.dumps({"settings": {"ablation": True}, "rows": []}))
    masks.write_text(json.dumps({"settings": {"ablation": False}, "rows": []}))
    with pytest.raises(SystemExit, match="summarize each kind separately"):
        quality.summarize([ablation, masks])
