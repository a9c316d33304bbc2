"""benchmarks/step_times.py --table: the rows and ratios of run.sh train-balanced's run folders."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import load_benchmark

step_times = load_benchmark("step_times.py", "step_times_under_test")


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
    lines = step_times.balanced_table(folders, vote_start=4)
    table = "\n".join(lines)
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
    lines = step_times.balanced_table(folders, vote_start=4)
    assert lines[2].endswith("| — |")  # no ns-eval: no PSNR
    assert "run wall 1.100×" in lines[-2] and "eval PSNR" not in lines[-2]
    only_votes = step_times.balanced_table(folders[1:], vote_start=4)
    assert only_votes[-1] == "no ratio: a method has no finished run"


def test_table_from_the_command_line(tmp_path, capsys):
    folders = [
        write_run(tmp_path / "1-splatfacto", "splatfacto", [4000] + [10] * 9, 50.0),
        write_run(tmp_path / "2-votesplat", "votesplat", [4000] + [11] * 9, 55.0),
    ]
    step_times.main(["--table", *map(str, folders), "--vote-start", "4"])
    printed = capsys.readouterr().out
    assert "| steps 1–3 | steps 4– |" in printed and "run wall 1.100×" in printed


@pytest.mark.parametrize("bad", ["two steps files", "two methods"])
def test_a_folder_that_is_not_one_run_is_not_finished(tmp_path, bad):
    folder = write_run(tmp_path / "1-votesplat", "votesplat", [4000] + [10] * 9, 50.0)
    if bad == "two steps files":
        (folder / "steps_synthetic_splatfacto.json").write_text((folder / "steps_synthetic_votesplat.json").read_text())
    else:
        result = json.loads((folder / "train_synthetic.json").read_text())
        result["methods"]["splatfacto"] = result["methods"]["votesplat"]
        (folder / "train_synthetic.json").write_text(json.dumps(result))
    assert step_times.run_row(folder, vote_start=4) is None


@pytest.mark.parametrize("phases", [False, True])
def test_step_times_record_every_step_and_wrap_the_phases_only_when_asked(phases, tmp_path, monkeypatch):
    """VOTESPLAT_STEP_TIMES=walls (train-balanced's default) times the steps and wraps none of the phases, whose
    wrappers would charge votesplat's more numerous calls; =1 wraps and records them."""
    import atexit
    import importlib

    from nerfstudio.engine.trainer import Trainer

    from votesplat_ns.ns.model import VoteSplatModel

    train_profile = load_benchmark("train_profile.py", "train_profile_under_test")
    at_exit = []
    monkeypatch.setattr(atexit, "register", at_exit.append)
    monkeypatch.setattr(Trainer, "train_iteration", lambda self, step: step)  # restored after the test
    model_module = importlib.import_module("votesplat_ns.ns.model")
    for module_name, class_name, name in train_profile.PHASES:  # what the install rebinds: restored too
        module = importlib.import_module(module_name)
        if class_name:
            owner = getattr(module, class_name)
            monkeypatch.setattr(owner, name, vars(owner)[name])  # a static method stays one
            continue
        monkeypatch.setattr(module, name, getattr(module, name))
        if hasattr(model_module, name):  # where the model imported it
            monkeypatch.setattr(model_module, name, getattr(model_module, name))
    before = VoteSplatModel.get_metrics_dict
    out = tmp_path / "steps.json"
    train_profile.install_step_times(str(out), phases)
    assert (VoteSplatModel.get_metrics_dict is not before) == phases
    for step in range(3):
        assert Trainer.train_iteration(None, step) == step
    at_exit[0]()
    record = json.loads(out.read_text())
    assert record["steps"] == [0, 1, 2] and len(record["wall_ms"]) == 3
    assert ("Trainer.train_iteration" in record["phases_ms"]) == phases


def test_vote_step_cost_can_leave_out_the_refinement_steps():
    """Votes every 2nd step from 4: 12 ms against 10 ms; every 100th step (a vote step here) takes 100 ms more, and
    the step after it 50 ms more. Left out, the difference is the vote step's own 2 ms."""
    walls = [12.0 if step >= 4 and step % 2 == 0 else 10.0 for step in range(400)]
    for step in (100, 200, 300):
        walls[step] += 100.0
        walls[step + 1] += 50.0
    record = {"steps": list(range(400)), "wall_ms": walls, "phases_ms": {}}
    (with_them,) = step_times.vote_step_cost(record, [(4, 400)], every=2, start=4)
    (without,) = step_times.vote_step_cost(record, [(4, 400)], every=2, start=4, skip_refinement=True)
    assert "difference mean +2.76 / median +2.00 ms" in with_them
    assert "198 vote steps" in with_them and "195 vote steps" in without and "195 others" in without
    assert "difference mean +2.00 / median +2.00 ms" in without


def test_psnr_over_seeds_takes_each_training_against_its_groups_first_and_leaves_out_unfinished_pairs(tmp_path, capsys):
    """benchmarks/psnr_seeds.py over train_side_by_side.sh's group folders: differences per group, their mean and
    standard error over the groups where both trainings trained and evaluated."""
    psnr_seeds = load_benchmark("psnr_seeds.py", "psnr_seeds_under_test")

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
    summary = psnr_seeds.summarize(psnr_seeds.read_groups(folders[::-1]))
    assert summary["baseline"] == "1_splatfacto" and [g["seed"] for g in summary["groups"]] == [42, 7, 1]
    votes = summary["trainings"]["2_votesplat"]
    assert votes["paired_groups"] == 2  # group 3 has no votesplat PSNR
    assert votes["difference_mean"] == pytest.approx(0.1)  # (+0.3 - 0.1) / 2
    assert votes["difference_std"] == pytest.approx(0.4 / 2**0.5)
    assert votes["difference_standard_error"] == pytest.approx(0.2)
    psnr_seeds.main([*map(str, folders), "--json", str(tmp_path / "psnr.json")])
    printed = capsys.readouterr().out
    assert "| 3 (1) | 29.000 | — | — |" in printed and "| 1 (42) | 30.000 | 30.300 | +0.300 |" in printed
    assert "2_votesplat − 1_splatfacto: mean **+0.100 dB** over 2 groups, std 0.283, standard error 0.200" in printed
    assert "group 3 (1), 2_votesplat: no PSNR: training timeout after 100 s, eval not run" in printed
    assert json.loads((tmp_path / "psnr.json").read_text())["trainings"]["2_votesplat"]["paired_groups"] == 2
    with pytest.raises(SystemExit, match="not a group folder"):
        psnr_seeds.read_groups([tmp_path])
    # a later call's groups pool with this one's: group 3 there pairs, so three pairs over two files
    psnr_seeds.main([str(folders[2]), "--json", str(tmp_path / "later.json")])
    later = json.loads((tmp_path / "later.json").read_text())
    later["groups"][0]["trainings"]["2_votesplat"], later["groups"][0]["unfinished"] = 29.6, {}
    (tmp_path / "later.json").write_text(json.dumps(later))
    capsys.readouterr()
    psnr_seeds.main(["--pool", str(tmp_path / "psnr.json"), str(tmp_path / "later.json")])
    printed = capsys.readouterr().out
    assert "| 3 (1) | 29.000 | — | — |" in printed and "| 4 (1) | 29.000 | 29.600 | +0.600 |" in printed
    assert "2_votesplat − 1_splatfacto: mean **+0.267 dB** over 3 groups" in printed  # (+0.3 - 0.1 + 0.6) / 3
    with pytest.raises(SystemExit, match=r"later.json is not a JSON written by psnr_seeds.py --json"):
        (tmp_path / "later.json").write_text("{}")
        psnr_seeds.pool_groups([tmp_path / "psnr.json", tmp_path / "later.json"])
    with pytest.raises(SystemExit):
        psnr_seeds.main([str(folders[0]), "--pool", str(tmp_path / "psnr.json")])
