"""benchmarks/quality.py's tables (per-seed rows grouped into mean ± std, the --summarize merge) and
benchmarks/sweep.py's family-set option."""

from __future__ import annotations

import json
import statistics
import sys

import pytest
from conftest import load_benchmark


@pytest.fixture(scope="module")
def quality():
    return load_benchmark("quality.py", "votesplat_quality_benchmark")


def row(variant, seed, miou, num_pred=5):
    return {
        "scene": "forward",
        "variant": variant,
        "seed": seed,
        "level": "instance",
        "miou": miou,
        "precision": 1.0,
        "recall": 0.5 + seed / 10,
        "purity": 0.9,
        "num_gt": 5,
        "num_pred": num_pred,
        "num_gaussians": 100,
        "train_seconds": 60.0,
    }


def parse_summary(table: str):
    lines = [line for line in table.splitlines() if line.startswith("|")]
    header = [cell.strip() for cell in lines[0].strip("|").split("|")]
    return [dict(zip(header, (cell.strip() for cell in line.strip("|").split("|")))) for line in lines[2:]]


def test_summary_groups_seeds_and_skips_failed_runs(quality):
    rows = [
        row("full", 0, 0.8),
        row("full", 1, 0.9),
        row("full", 2, 1.0, num_pred=8),
        row("no distortion", 0, 0.7),
        {"scene": "forward", "variant": "no distortion", "seed": 1, "error": "RuntimeError: x"},
    ]
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


def level_scores(miou, valid=None, num_pred=4):
    scores = {
        "miou": miou,
        "precision": 0.8,
        "recall": 0.7,
        "purity": 0.9,
        "completeness": 0.95,
        "scores_2d": {"num_gt": 5},
        "num_predicted_instances": num_pred,
    }
    if valid is not None:
        scores.update(miou_valid_views=valid, precision_valid_views=0.85, recall_valid_views=None, num_valid_views=5)
    return scores


def test_level_row_reads_the_valid_view_scores_where_reported(quality):
    metrics = {
        "num_gaussians": 1234,
        "view_names": ["a", "b", "c", "d", "e", "f"],
        "levels": {"instance": level_scores(0.6, valid=0.9), "part": level_scores(0.5)},
    }
    instance, part = quality.level_row(metrics, "instance"), quality.level_row(metrics, "part")
    assert (instance["miou"], instance["miou_views"], instance["miou_all_views"]) == (0.9, "valid 5/6", 0.6)
    assert (instance["precision"], instance["recall"]) == (0.85, 0.7)  # no valid-view recall reported: all views
    assert (part["miou"], part["miou_views"], part["miou_all_views"], part["precision"]) == (0.5, "all", 0.5, 0.8)
    assert instance["num_gt"] == 5 and instance["num_pred"] == 4 and instance["num_gaussians"] == 1234
    missing = quality.level_row(metrics, "object")
    assert "error" in missing and "'object'" in missing["error"]


def scene_row(scene, level, miou, masks="gt"):
    metrics = {"num_gaussians": 100, "levels": {level: level_scores(miou / 2, valid=miou)}}
    return {
        "scene": scene,
        "masks": masks,
        "seed": 42,
        "train_seconds": 60.0,
        **quality_module().level_row(metrics, level),
    }


def quality_module():
    return sys.modules["votesplat_quality_benchmark"]


def test_merge_gives_rows_per_scene_and_the_mean_over_scenes(quality, tmp_path):
    files = []
    for scene, mious in (("family_1", (0.9, 0.5)), ("family_2", (0.7, 0.3)), ("family_3", None)):
        if mious is None:
            rows = [
                {"scene": scene, "masks": "gt", "seed": 42, "level": level, "error": "RuntimeError: CUDA out of memory"}
                for level in ("instance", "part")
            ]
        else:
            rows = [scene_row(scene, "instance", mious[0]), scene_row(scene, "part", mious[1])]
        path = tmp_path / scene / "quality.json"
        path.parent.mkdir()
        path.write_text(json.dumps({"settings": {"ablation": False}, "rows": rows}))
        files.append(path)
    text = quality.merge(files)
    per_scene, means = text.split("Mean over scenes:")
    per_scene = [r for r in parse_summary(per_scene) if not r["mIoU"].startswith("failed")]
    assert {(r["scene"], r["level"], r["mIoU"]) for r in per_scene} == {
        ("family_1", "instance", "0.900"),
        ("family_1", "part", "0.500"),
        ("family_2", "instance", "0.700"),
        ("family_2", "part", "0.300"),
    }
    assert all(r["views"] == "valid" and float(r["mIoU all views"]) == float(r["mIoU"]) / 2 for r in per_scene)
    assert sum("failed: RuntimeError" in line for line in text.splitlines()) == 2
    mean = {r["level"]: r for r in parse_summary(means)}
    assert mean["instance"]["mIoU"] == "0.800" and mean["part"]["mIoU"] == "0.400"
    assert mean["instance"]["scene"] == "mean of 2 (1 failed: family_3)"
    assert quality.main(["--merge", *map(str, files)]) == 0
    ablation = tmp_path / "ablation.json"
    ablation.write_text(json.dumps({"settings": {"ablation": True}, "rows": []}))
    with pytest.raises(SystemExit, match="--merge takes quality.json"):
        quality.merge([ablation])


@pytest.fixture(scope="module")
def sweep():
    return load_benchmark("sweep.py", "votesplat_sweep_benchmark")


def test_sweep_family_option_reads_the_set_folder(sweep, tmp_path):
    from votesplat_ns.eval.synthetic.family import SET_MANIFEST, TEST_SEEDS, TUNING_SEEDS, scene_folder

    with pytest.raises(SystemExit):
        sweep.parse_args(["--family", "test", "--family-dir", str(tmp_path)])  # no family_set.json
    (tmp_path / SET_MANIFEST).write_text(json.dumps({"set": "test", "seeds": list(TEST_SEEDS)}))
    for seed in TEST_SEEDS:
        (tmp_path / scene_folder(seed)).mkdir()
        (tmp_path / scene_folder(seed) / "transforms.json").write_text("{}")
    args = sweep.parse_args(["--family", "test", "--family-dir", str(tmp_path)])
    assert args.scenes == [tmp_path / scene_folder(seed) for seed in TEST_SEEDS]
    assert sweep.LEVELS == ("instance", "part")  # every run is scored at both levels
    with pytest.raises(SystemExit):
        sweep.parse_args(["--family", "tuning", "--family-dir", str(tmp_path)])  # the folder holds the test set
    with pytest.raises(SystemExit):
        sweep.parse_args(["--family", "test", "--family-dir", str(tmp_path), "--scenes", str(tmp_path)])
    (tmp_path / SET_MANIFEST).write_text(json.dumps({"set": "test", "seeds": list(TUNING_SEEDS)}))
    with pytest.raises(SystemExit):
        sweep.parse_args(["--family", "test", "--family-dir", str(tmp_path)])  # seeds that are not this code's test set


def test_sweep_rows_carry_the_object_scores_and_the_table_averages_them(sweep):
    def level(list_precision, ghost, purity):
        return {
            "miou": 0.9,
            "miou_valid_views": 0.9,
            "precision": 0.8,
            "recall": 0.7,
            "completeness": 0.95,
            "num_predicted_instances": 4,
            "num_gt_objects": 3,
            "mean_completeness_3d": 0.9,
            "mean_purity_3d": purity,
            "list_precision": list_precision,
            "ap50_3d": 0.5,
            "ghost_percent": ghost,
        }

    rows = []
    for scene, (precision, ghost, purity) in (("a", (0.75, 2.0, 0.8)), ("b", (0.25, 4.0, None))):
        metrics = {"levels": {"instance": level(precision, ghost, purity)}}
        rows.append({"scene": scene, "masks": "gt", "train": "default", "cluster": "c", "seed": 0, "level": "instance"})
        rows[-1].update(sweep.score(metrics, "instance"))
    assert rows[0]["list_precision"] == 0.75 and rows[0]["ghost_percent"] == 2.0 and rows[1]["purity_object"] is None
    header, _, means = sweep.table(rows).splitlines()[:3]
    cells = dict(
        zip([c.strip() for c in header.strip("|").split("|")], [c.strip() for c in means.strip("|").split("|")])
    )
    assert cells["list precision"] == "0.500" and cells["ghost %"] == "3.0" and cells["AP@50 3D"] == "0.500"
    assert cells["purity/object"] == "0.800"  # the scene without a matched object is left out, not counted as 0
    assert cells["#objects"] == "3.0" and cells["completeness/object"] == "0.900"
