"""The instance-quality tools, run as scripts: benchmarks/quality.py's tables over stored runs (per-seed rows
grouped into mean ± std by --summarize, parallel runs' rows merged by --merge), benchmarks/sweep.py's --summarize
table and its family-set checks."""

from __future__ import annotations

import json
import statistics
from pathlib import Path

import numpy as np
from conftest import BENCHMARKS, DEMO_SCENE, run_benchmark


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


def parse_table(table: str):
    lines = [line for line in table.splitlines() if line.startswith("|")]
    header = [cell.strip() for cell in lines[0].strip("|").split("|")]
    return [dict(zip(header, (cell.strip() for cell in line.strip("|").split("|")))) for line in lines[2:]]


def stored(path: Path, rows, ablation: bool) -> Path:
    """A quality.json / ablation.json as quality.py writes it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"settings": {"ablation": ablation}, "rows": rows}))
    return path


def test_summarize_groups_seeds_of_parallel_runs_and_skips_failed_ones(tmp_path):
    files = [
        stored(tmp_path / "a" / "ablation.json", [row("full", 0, 0.8), row("no distortion", 0, 0.7)], True),
        stored(tmp_path / "b" / "ablation.json", [row("full", 1, 0.9)], True),
        stored(
            tmp_path / "c" / "ablation.json",
            [
                row("full", 2, 1.0, num_pred=8),
                {"scene": "forward", "variant": "no distortion", "seed": 1, "error": "RuntimeError: x"},
            ],
            True,
        ),
    ]
    printed = run_benchmark("quality.py", "--summarize", *map(str, files)).stdout
    summary = {entry["variant"]: entry for entry in parse_table(printed)}
    assert summary["full"]["runs"] == "3" and summary["no distortion"]["runs"] == "1"
    assert summary["full"]["mIoU"] == f"{0.9:.3f} ± {statistics.stdev([0.8, 0.9, 1.0]):.3f}"
    assert summary["full"]["recall"] == f"{0.6:.3f} ± {statistics.stdev([0.5, 0.6, 0.7]):.3f}"
    assert summary["full"]["#pred"] == f"{6.0:.1f} ± {statistics.stdev([5, 5, 8]):.1f}"
    assert summary["no distortion"]["mIoU"] == "0.700 ± 0.000"  # one run: no spread to report


def test_summarize_refuses_unreadable_or_mixed_files(tmp_path):
    broken = tmp_path / "ablation.json"
    broken.write_text("{not json")
    refused = run_benchmark("quality.py", "--summarize", str(broken), expect_ok=False)
    assert refused.returncode != 0 and "cannot read" in refused.stderr
    ablation = stored(tmp_path / "a.json", [], True)
    masks = stored(tmp_path / "q.json", [], False)
    refused = run_benchmark("quality.py", "--summarize", str(ablation), str(masks), expect_ok=False)
    assert refused.returncode != 0 and "summarize each kind separately" in refused.stderr


def scene_row(scene, level, miou):
    """A row as quality.py stores it: mIoU over the valid views, half of it over all views."""
    return {
        "scene": scene,
        "masks": "gt",
        "seed": 42,
        "train_seconds": 60.0,
        "level": level,
        "miou": miou,
        "miou_views": "valid",
        "miou_all_views": miou / 2,
        "precision": 0.8,
        "recall": 0.7,
        "purity": 0.9,
        "completeness": 0.95,
        "num_gt": 5,
        "num_pred": 4,
        "num_gaussians": 100,
    }


def test_merge_gives_rows_per_scene_and_the_mean_over_scenes(tmp_path):
    files = []
    for scene, mious in (("family_1", (0.9, 0.5)), ("family_2", (0.7, 0.3)), ("family_3", None)):
        if mious is None:
            rows = [
                {"scene": scene, "masks": "gt", "seed": 42, "level": level, "error": "RuntimeError: CUDA out of memory"}
                for level in ("instance", "part")
            ]
        else:
            rows = [scene_row(scene, "instance", mious[0]), scene_row(scene, "part", mious[1])]
        files.append(stored(tmp_path / scene / "quality.json", rows, False))
    text = run_benchmark("quality.py", "--merge", *map(str, files)).stdout
    per_scene, means = text.split("Mean over scenes:")
    per_scene = [r for r in parse_table(per_scene) if not r["mIoU"].startswith("failed")]
    assert {(r["scene"], r["level"], r["mIoU"]) for r in per_scene} == {
        ("family_1", "instance", "0.900"),
        ("family_1", "part", "0.500"),
        ("family_2", "instance", "0.700"),
        ("family_2", "part", "0.300"),
    }
    assert all(r["views"] == "valid" and float(r["mIoU all views"]) == float(r["mIoU"]) / 2 for r in per_scene)
    assert sum("failed: RuntimeError" in line for line in text.splitlines()) == 2
    mean = {r["level"]: r for r in parse_table(means)}
    assert mean["instance"]["mIoU"] == "0.800" and mean["part"]["mIoU"] == "0.400"
    assert mean["instance"]["scene"] == "mean of 2 (1 failed: family_3)"
    ablation = stored(tmp_path / "ablation.json", [], True)
    refused = run_benchmark("quality.py", "--merge", str(ablation), expect_ok=False)
    assert refused.returncode != 0 and "--merge takes quality.json" in refused.stderr


def test_sweep_family_option_takes_only_this_codes_test_set(tmp_path):
    """--family test refuses a folder without the set's manifest, a folder of the other set, a manifest whose seeds
    are not this code's test set, and --scenes beside it (defaults are chosen on the tuning set only)."""
    from votesplat_ns.eval.synthetic.family import SET_MANIFEST, TEST_SEEDS, TUNING_SEEDS, scene_folder

    def refused(*args: str) -> str:
        done = run_benchmark("sweep.py", *args, "--work-dir", str(tmp_path / "work"), expect_ok=False)
        assert done.returncode == 2, done.stderr[-2000:]  # argparse's usage error, before any training
        return done.stderr

    family = ("--family-dir", str(tmp_path))
    refused("--family", "test", *family)  # no family_set.json
    (tmp_path / SET_MANIFEST).write_text(json.dumps({"set": "test", "seeds": list(TEST_SEEDS)}))
    for seed in TEST_SEEDS:
        (tmp_path / scene_folder(seed)).mkdir()
        (tmp_path / scene_folder(seed) / "transforms.json").write_text("{}")
    assert "holds the test set, not tuning" in refused("--family", "tuning", *family)
    assert "either --scenes or --family" in refused("--family", "test", *family, "--scenes", str(tmp_path))
    (tmp_path / SET_MANIFEST).write_text(json.dumps({"set": "test", "seeds": list(TUNING_SEEDS)}))
    refused("--family", "test", *family)  # seeds that are not this code's test set
    assert not (tmp_path / "work").exists()


def test_sweep_table_averages_the_object_scores_over_scenes(tmp_path):
    def scores(scene, list_precision, ghost, purity):
        return {
            "scene": scene,
            "masks": "gt",
            "train": "default",
            "cluster": "c",
            "seed": 0,
            "level": "instance",
            "miou": 0.9,
            "miou_all_views": 0.9,
            "precision": 0.8,
            "recall": 0.7,
            "completeness": 0.95,
            "num_pred": 4,
            "num_gt": 3,
            "completeness_object": 0.9,
            "purity_object": purity,
            "list_precision": list_precision,
            "ap50_3d": 0.5,
            "ghost_percent": ghost,
        }

    rows = [scores("a", 0.75, 2.0, 0.8), scores("b", 0.25, 4.0, None)]
    path = tmp_path / "sweep.json"
    path.write_text(json.dumps({"rows": rows}))
    (cells,) = parse_table(run_benchmark("sweep.py", "--summarize", str(path)).stdout)
    assert cells["list precision"] == "0.500" and cells["ghost %"] == "3.0" and cells["AP@50 3D"] == "0.500"
    assert cells["purity/object"] == "0.800"  # the scene without a matched object is left out, not counted as 0
    assert cells["#objects"] == "3.0" and cells["completeness/object"] == "0.900"
    assert cells["worst scene"] == "0.900 (a)" and cells["runs"] == "2"


def benchmark_module(name: str, monkeypatch):
    """benchmarks/<name>.py imported (benchmarks/ is no package; its scripts import their siblings)."""
    import importlib.util

    monkeypatch.syspath_prepend(str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_replayed_rules_give_the_evals_instances_back_and_score_a_variant_against_them(
    trained_demo, tmp_path, monkeypatch
):
    """benchmarks/replay_rules.py: the dump of a trained run replays to the instances and scores that ``votesplat
    eval`` gave (the tool stops otherwise), without reading or writing the run's kept instances; a variant that
    changes them is scored against the defaults at both levels."""
    kept = trained_demo.parent / "votesplat_instances" / "instances.json"
    kept_before = kept.read_bytes() if kept.exists() else None
    run_benchmark("replay_rules.py", "dump", "--config", str(trained_demo), "--out", str(tmp_path))
    assert (kept.read_bytes() if kept.exists() else None) == kept_before
    dump = tmp_path / f"{trained_demo.parent.name}.npz"
    # the dump keeps the mask check's training views: its tables computed again from them are the check's
    replay_rules = benchmark_module("replay_rules", monkeypatch)
    dumped = replay_rules.load(dump)
    for level in (0, 1):
        np.testing.assert_array_equal(replay_rules.retable(dumped, level), dumped[f"table_{level}"])
    assert (replay_rules.retable(dumped, 0, depth_tolerance=0.0) >= 0).sum() < (dumped["table_0"] >= 0).sum()
    # rebuilt from the scene alone (for dumps without them), the views and masks are the run's
    rebuilt = replay_rules.training_views(DEMO_SCENE, tmp_path / "rebuilt")
    assert set(rebuilt) == {key for key in dumped if key.startswith("train_")}
    for key, value in rebuilt.items():
        np.testing.assert_array_equal(value, dumped[key])
    noisy = parse_table(run_benchmark("replay_rules.py", "noisy-evidence", "--pair", str(dump), str(DEMO_SCENE)).stdout)
    assert len(noisy) == 1 and float(noisy[0]["mask pixels changed %"]) > 0 and noisy[0]["ghost_percent"] != "-"
    table = run_benchmark(
        "replay_rules.py", "replay", str(dump), "--variant", "same:objects=True", "none:objects=False"
    )
    rows = {(r["level"], r["variant"]): r for r in parse_table(table.stdout)}
    assert set(rows) == {(level, name) for level in ("0", "1") for name in ("same", "none")}
    for level in ("0", "1"):
        assert rows[level, "same"]["Gaussians moved"] == "0" and "→" not in "".join(rows[level, "same"].values())
    # without the whole-object rules the hidden Gaussians stay background: instances lose Gaussians
    assert int(rows["0", "none"]["Gaussians moved"]) > 0 and "→" in rows["0", "none"]["mean_completeness_3d"]


def test_replay_counts_a_gaussian_as_moved_when_its_instance_changes_not_when_instances_are_renumbered(monkeypatch):
    """The rules renumber instances by size, so one Gaussian added to an instance can swap two ids, and comparing ids
    would count every Gaussian of both (5,151 for 1,253 moved on a tuning run); the replay's "Gaussians moved" pairs
    the instances by what they share."""
    moved = benchmark_module("replay_rules", monkeypatch).moved_gaussians

    before = np.array([0, 0, 0, 1, 1, -1, -1, 2])
    assert moved(before, before) == 0
    assert moved(before, np.array([1, 1, 1, 0, 0, -1, -1, 2])) == 0  # the same instances, other ids
    assert moved(before, np.array([1, 1, 1, 0, 0, 0, -1, 2])) == 1  # a background Gaussian joins, ids swapped
    assert moved(before, np.array([0, 0, 1, 1, 1, -1, -1, 2])) == 1  # one Gaussian changes instance
    assert moved(before, np.full(8, -1)) == 6  # every instance's Gaussians to the background
    assert moved(np.array([-1, -1]), np.array([0, 0])) == 2  # background never pairs with an instance


def test_the_sweeps_noisy_masks_carry_sam_like_errors_as_the_noise_command_and_quality_benchmark_do(
    monkeypatch, tmp_path
):
    """``sweep.py --masks noisy`` trains on the GT masks with ``SAM_LIKE_NOISE``, the defaults of ``votesplat eval
    noise`` and of ``quality.py`` (``MaskNoise()`` alone, every rate 0, would leave the GT masks unchanged)."""
    import dataclasses

    from votesplat_ns.cli.evaluate_cli import WriteNoisyMasks
    from votesplat_ns.eval.mask_noise import NOISE_MANIFEST_NAME, SAM_LIKE_NOISE

    folder = benchmark_module("sweep", monkeypatch).noisy_masks(DEMO_SCENE, tmp_path / "noisy")
    manifest = json.loads((folder / NOISE_MANIFEST_NAME).read_text())
    assert manifest["noise"] == dataclasses.asdict(SAM_LIKE_NOISE)
    assert manifest["views_changed"]["instance"] >= manifest["num_views"] // 2 and manifest["views_changed"]["part"] > 0
    assert WriteNoisyMasks(data=DEMO_SCENE, output=tmp_path / "x").noise() == SAM_LIKE_NOISE
    args = benchmark_module("quality", monkeypatch).parse_args([])
    rates = ("split_rate", "merge_rate", "jitter_rate", "drop_rate")
    assert {rate: getattr(args, rate) for rate in rates} == {rate: getattr(SAM_LIKE_NOISE, rate) for rate in rates}
