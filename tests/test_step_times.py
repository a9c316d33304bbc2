"""The training-time comparison's tools, run as scripts: benchmarks/step_times.py --table over run.sh
train-balanced's run folders, and benchmarks/psnr_seeds.py over train_side_by_side.sh's group folders."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import run_benchmark


def table_lines(*folders: Path, vote_start: int = 4) -> list:
    printed = run_benchmark("step_times.py", "--table", *map(str, folders), "--vote-start", str(vote_start)).stdout
    return printed.rstrip("\n").splitlines()


def write_run(folder: Path, method: str, walls_ms, wall_s: float, psnr=None, status: str = "ok") -> Path:
    """A run folder as train-balanced leaves it: one steps file and one train file."""
    folder.mkdir(parents=True)
    steps = {
        "steps": list(range(len(walls_ms))),
        "wall_ms": list(walls_ms),
        "phases_ms": {},
        "setup_s": 5.0,
        "tail_s": 0.1,
        "total_s": 5.1 + sum(walls_ms) / 1e3,
    }
    (folder / f"steps_synthetic_{method}.json").write_text(json.dumps(steps))
    result = {"status": status, "wall_s": wall_s, "process": {"wall_s": wall_s - 2.0}}
    if psnr is not None:
        result["eval"] = {"psnr": psnr}
    (folder / "train_synthetic.json").write_text(json.dumps({"methods": {method: result}}))
    return folder


def test_table_gives_votesplats_means_over_splatfactos_and_leaves_out_unfinished_runs(tmp_path):
    # 10 steps, votes from step 4: splatfacto 10 ms a step, votesplat 12 ms from step 4 on; step 0 4 s (and the
    # first splatfacto run's 8 s, the machine's first training)
    folders = [
        write_run(tmp_path / "1-splatfacto", "splatfacto", [8000] + [10] * 9, 100.0, psnr=30.0),
        write_run(tmp_path / "2-votesplat", "votesplat", [4000] + [10] * 3 + [12] * 6, 105.0, psnr=30.3),
        write_run(tmp_path / "3-votesplat", "votesplat", [4000] + [10] * 3 + [12] * 6, 111.0, psnr=29.9),
        write_run(tmp_path / "4-splatfacto", "splatfacto", [4000] + [10] * 9, 100.0, psnr=30.1),
        write_run(tmp_path / "5-splatfacto", "splatfacto", [4000] + [10] * 9, 10.0, status="timeout"),
        tmp_path / "6-votesplat",  # never started
    ]
    lines = table_lines(*folders)
    table = "\n".join(lines)
    assert "| steps 1–3 | steps 4– |" in lines[0]
    assert "| 1-splatfacto | splatfacto | 100.0 (98.0) s | 5.00 s | 8.00 s | 0.03 s | 0.06 s | 30.000 |" in table
    assert "| 2-votesplat | votesplat | 105.0 (103.0) s | 5.00 s | 4.00 s | 0.03 s | 0.07 s | 30.300 |" in table
    assert "| 5-splatfacto | | not finished |" in table and "| 6-votesplat | | not finished |" in table
    summary = lines[-2]
    # means over the finished runs: (105 + 111) / 2 / 100; process (103 + 109) / 2 / 98; steps 1-9: 0.102 / 0.090
    assert "(2 and 2 runs)" in summary
    assert "run wall 1.080×" in summary and f"process {106 / 98:.3f}×" in summary
    assert f"steps 1– {0.102 / 0.090:.3f}×" in summary
    assert "a step from 4 on +2.00 ms" in summary
    assert "eval PSNR +0.050 dB" in summary  # (30.3 + 29.9) / 2 - (30.0 + 30.1) / 2
    assert "step 0 per run: 8.00, 4.00, 4.00, 4.00 s" in lines[-1]


def test_table_without_eval_or_without_a_method_says_so(tmp_path):
    folders = [
        write_run(tmp_path / "1-splatfacto", "splatfacto", [4000] + [10] * 9, 50.0),
        write_run(tmp_path / "2-votesplat", "votesplat", [4000] + [11] * 9, 55.0),
    ]
    lines = table_lines(*folders)
    assert lines[2].endswith("| — |")  # no ns-eval: no PSNR
    assert "run wall 1.100×" in lines[-2] and "eval PSNR" not in lines[-2]
    assert table_lines(folders[1])[-1] == "no ratio: a method has no finished run"


@pytest.mark.parametrize("bad", ["two steps files", "two methods"])
def test_a_folder_that_is_not_one_run_is_not_finished(tmp_path, bad):
    folder = write_run(tmp_path / "1-votesplat", "votesplat", [4000] + [10] * 9, 50.0)
    if bad == "two steps files":
        (folder / "steps_synthetic_splatfacto.json").write_text((folder / "steps_synthetic_votesplat.json").read_text())
    else:
        result = json.loads((folder / "train_synthetic.json").read_text())
        result["methods"]["splatfacto"] = result["methods"]["votesplat"]
        (folder / "train_synthetic.json").write_text(json.dumps(result))
    assert table_lines(folder)[2].startswith("| 1-votesplat | | not finished |")


def test_psnr_over_seeds_takes_each_training_against_its_groups_first_and_leaves_out_unfinished_pairs(tmp_path):
    """psnr_seeds.py over train_side_by_side.sh's group folders: differences per group, their mean and standard
    error over the groups where both trainings trained and evaluated; --pool joins several calls' groups."""

    def group(index: int, seed: int, *runs) -> Path:
        folder = tmp_path / f"g{index}-seed{seed}"
        for k, (training, psnr, status) in enumerate(runs, start=1):
            run = folder / f"{k}_{training}"
            run.mkdir(parents=True)
            method = "splatfacto" if training == "splatfacto" else "votesplat"
            entry = {"status": status, "eval_status": "ok" if status == "ok" else "not run", "eval": {"psnr": psnr}}
            (run / "train_fox.json").write_text(json.dumps({"methods": {method: entry}}))
        return folder

    folders = [
        group(1, 42, ("splatfacto", 30.0, "ok"), ("votesplat", 30.3, "ok")),
        group(2, 7, ("splatfacto", 31.0, "ok"), ("votesplat", 30.9, "ok")),
        group(3, 1, ("splatfacto", 29.0, "ok"), ("votesplat", 20.0, "timeout after 100 s")),
    ]
    first = tmp_path / "psnr.json"
    printed = run_benchmark("psnr_seeds.py", *map(str, folders[::-1]), "--json", str(first)).stdout
    summary = json.loads(first.read_text())
    assert summary["baseline"] == "1_splatfacto" and [g["seed"] for g in summary["groups"]] == [42, 7, 1]
    votes = summary["trainings"]["2_votesplat"]
    assert votes["paired_groups"] == 2  # group 3 has no votesplat PSNR
    assert votes["difference_mean"] == pytest.approx(0.1)  # (+0.3 - 0.1) / 2
    assert votes["difference_std"] == pytest.approx(0.4 / 2**0.5)
    assert votes["difference_standard_error"] == pytest.approx(0.2)
    assert "| 3 (1) | 29.000 | — | — |" in printed and "| 1 (42) | 30.000 | 30.300 | +0.300 |" in printed
    assert "2_votesplat − 1_splatfacto: mean **+0.100 dB** over 2 groups, std 0.283, standard error 0.200" in printed
    assert "group 3 (1), 2_votesplat: no PSNR: training timeout after 100 s, eval not run" in printed
    refused = run_benchmark("psnr_seeds.py", str(tmp_path), expect_ok=False)
    assert refused.returncode != 0 and "not a group folder" in refused.stderr
    # a later call's groups pool with this one's: group 3 there pairs, so three pairs over two files
    later = tmp_path / "later.json"
    run_benchmark("psnr_seeds.py", str(folders[2]), "--json", str(later))
    record = json.loads(later.read_text())
    record["groups"][0]["trainings"]["2_votesplat"], record["groups"][0]["unfinished"] = 29.6, {}
    later.write_text(json.dumps(record))
    printed = run_benchmark("psnr_seeds.py", "--pool", str(first), str(later)).stdout
    assert "| 3 (1) | 29.000 | — | — |" in printed and "| 4 (1) | 29.000 | 29.600 | +0.600 |" in printed
    assert "2_votesplat − 1_splatfacto: mean **+0.267 dB** over 3 groups" in printed  # (+0.3 - 0.1 + 0.6) / 3
    later.write_text("{}")
    refused = run_benchmark("psnr_seeds.py", "--pool", str(first), str(later), expect_ok=False)
    assert refused.returncode != 0 and "later.json is not a JSON written by psnr_seeds.py --json" in refused.stderr
    both = run_benchmark("psnr_seeds.py", str(folders[0]), "--pool", str(first), expect_ok=False)
    assert both.returncode != 0 and "either group folders or --pool" in both.stderr
