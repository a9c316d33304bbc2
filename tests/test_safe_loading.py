"""Opening someone else's run runs none of its code: a run's config.yml and checkpoints are read safely.

A config.yml is a Python object dump; ``ns/run_config.py`` reads it with an allow-list (nerfstudio's and
votesplat's config dataclasses, their ``_target`` classes, paths, enums, tuples). Checkpoints are read with
``weights_only=True`` (``ns/run.py``, ``ns/trainer.py``). Every payload here only creates a marker file, and
every test checks that the marker was not made. No training: configs are dumped as ns-train dumps them.
"""

from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import List

import pytest
import torch
import yaml
from conftest import BIN

from votesplat_ns.errors import VoteSplatInputError
from votesplat_ns.eval.synthetic.labels import write_scene_labels
from votesplat_ns.ns.method import trainer_config_in_process
from votesplat_ns.ns.run import latest_checkpoint, load_gaussians, load_run
from votesplat_ns.ns.run_config import RefusedTag, load_run_config, parse_run_config
from votesplat_ns.ns.trainer import resume_state

DEMO_SCENE = Path(__file__).resolve().parents[1] / "votesplat_ns" / "data" / "demo"


def votesplat_config(output_dir: Path):
    return trainer_config_in_process(DEMO_SCENE, output_dir, 10, 5)


def splatfacto_config(output_dir: Path):
    from nerfstudio.configs.method_configs import all_methods

    config = copy.deepcopy(all_methods["splatfacto"])
    config.data = DEMO_SCENE
    config.output_dir = output_dir
    config.set_timestamp()
    return config


class Payload:
    """Pickles as a call of os.system that makes ``marker``: what a planted checkpoint would do."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


# ------------------------------------------------------------------ config.yml
@pytest.mark.parametrize("make_config", [votesplat_config, splatfacto_config], ids=["votesplat", "splatfacto"])
def test_a_real_config_loads_to_the_object_nerfstudio_dumped(make_config, tmp_path):
    config = make_config(tmp_path / "outputs")
    text = yaml.dump(config)  # what ExperimentConfig.save_config writes
    assert "!!python/name:" in text and "!!python/object/apply:pathlib" in text and "!!python/tuple" in text
    loaded = parse_run_config(text)
    assert type(loaded) is type(config)
    assert loaded == config
    assert loaded == yaml.load(text, Loader=yaml.Loader)  # what nerfstudio's eval_setup would have built
    assert yaml.dump(loaded) == text
    assert loaded.pipeline.model._target is config.pipeline.model._target


def test_the_votesplat_config_resumes_through_the_safe_trainer(tmp_path):
    from votesplat_ns.ns.trainer import VoteSplatTrainer

    config = parse_run_config(yaml.dump(votesplat_config(tmp_path)))
    assert config._target is VoteSplatTrainer


def test_classes_under_the_module_paths_of_earlier_layouts_load_from_where_they_live_now():
    from votesplat_ns.ns.datamanager import VoteDataManager
    from votesplat_ns.ns.model import VoteSplatModel, VoteSplatModelConfig

    text = """
model_target: !!python/name:votesplat_ns.model.VoteSplatModel ''
dm_target: !!python/name:votesplat_ns.datamanager.VoteDataManager ''
model: !!python/object:votesplat_ns.model.VoteSplatModelConfig {sh_degree: 2}
split_model: !!python/object:votesplat_ns.ns.model_config.VoteSplatModelConfig {sh_degree: 1}
"""
    loaded = parse_run_config(text)
    assert loaded["model_target"] is VoteSplatModel and loaded["dm_target"] is VoteDataManager
    assert type(loaded["model"]) is VoteSplatModelConfig and loaded["model"].sh_degree == 2
    assert type(loaded["split_model"]) is VoteSplatModelConfig and loaded["split_model"].sh_degree == 1
    # a class of another version is named as such, not as a payload
    gone = "model: !!python/object:votesplat_ns.ns.no_such_module.VoteSplatModelConfig {}\n"
    with pytest.raises(RefusedTag, match="votesplat_ns.ns.no_such_module is not installed") as refused:
        parse_run_config(gone)
    assert refused.value.other_version


def test_a_run_of_another_version_is_named_as_such_in_one_line(tmp_path):
    config = tmp_path / "config.yml"
    config.write_text("method_name: votesplat\nmodel: !!python/object:votesplat_ns.ns.model.NoSuchConfig {}\n")
    with pytest.raises(VoteSplatInputError) as error:
        load_run_config(config)
    message = str(error.value)
    assert "\n" not in message and str(config) in message and "line 2" in message
    assert "another version" in message and "could run code" not in message


REAL_LINE = "method_name: votesplat\n"
APPLY_OS_SYSTEM = "!!python/object/apply:os.system ['touch {marker}']"
# (what is planted, the tag refused: for a call nested in a path or an enum, the path's or the enum's)
PAYLOADS = {
    "apply os.system": (APPLY_OS_SYSTEM, "!!python/object/apply:os.system"),
    "apply subprocess": (
        "!!python/object/apply:subprocess.check_call [['touch', '{marker}']]",
        "!!python/object/apply:subprocess.check_call",
    ),
    "new os.system": ("!!python/object/new:os.system ['touch {marker}']", "!!python/object/new:os.system"),
    "function of a nerfstudio module": (
        "!!python/object/apply:nerfstudio.utils.eval_utils.eval_setup ['{marker}']",
        "!!python/object/apply:nerfstudio.utils.eval_utils.eval_setup",
    ),
    "name imported into a nerfstudio module": (
        "!!python/object/apply:nerfstudio.utils.eval_utils.Path ['{marker}']",
        "!!python/object/apply:nerfstudio.utils.eval_utils.Path",
    ),
    "a function as _target": ("!!python/name:os.system ''", "!!python/name:os.system"),
    "a nerfstudio function as _target": (
        "!!python/name:nerfstudio.utils.eval_utils.eval_setup ''",
        "!!python/name:nerfstudio.utils.eval_utils.eval_setup",
    ),
    "a module": ("!!python/module:os ''", "!!python/module:os"),
    "a class that is not a config": (
        "!!python/object:nerfstudio.engine.trainer.Trainer {{}}",
        "!!python/object:nerfstudio.engine.trainer.Trainer",
    ),
    "a method replaced by a field": (
        "!!python/object:nerfstudio.engine.trainer.TrainerConfig {{setup: 1}}",
        "!!python/object:nerfstudio.engine.trainer.TrainerConfig",
    ),
    "a path of a call": (
        "!!python/object/apply:pathlib.PosixPath [" + APPLY_OS_SYSTEM + "]",
        "!!python/object/apply:pathlib.PosixPath",
    ),
    "an enum of a call": (
        "!!python/object/apply:nerfstudio.utils.writer.EventName [" + APPLY_OS_SYSTEM + "]",
        "!!python/object/apply:nerfstudio.utils.writer.EventName",
    ),
    "a local tag": ("!payload 1", "!payload"),
}


@pytest.mark.parametrize("payload, tag", list(PAYLOADS.values()), ids=list(PAYLOADS))
def test_a_payload_anywhere_in_a_real_config_is_refused_and_runs_nothing(payload, tag, tmp_path):
    marker = tmp_path / "ran"
    text = yaml.dump(votesplat_config(tmp_path / "outputs"))
    assert REAL_LINE in text
    line = text[: text.index(REAL_LINE)].count("\n") + 1
    planted = text.replace(REAL_LINE, f"method_name: {payload.format(marker=marker)}\n")
    with pytest.raises(RefusedTag) as refused:
        parse_run_config(planted)
    assert (refused.value.tag, refused.value.line) == (tag, line)
    assert not marker.exists()

    config_path = tmp_path / "config.yml"
    config_path.write_text(planted)
    with pytest.raises(VoteSplatInputError) as error:
        load_run_config(config_path)
    message = str(error.value)
    assert message.startswith(f"--load-config {config_path}: refused to load tag {tag} at line {line} ("), message
    assert "\n" not in message
    assert not marker.exists()


def test_a_yaml_that_is_no_run_config_is_named_as_such(tmp_path):
    for name, text in (("list.yml", "- 1\n- 2\n"), ("broken.yml", "a: [1, 2\n"), ("binary.yml", None)):
        path = tmp_path / name
        if text is None:
            path.write_bytes(b"\xff\xfe\x00garbage")
        else:
            path.write_text(text)
        with pytest.raises(VoteSplatInputError, match=f"{path}: not a nerfstudio run config"):
            load_run_config(path)


def commands(config: Path, tmp_path: Path, labels: Path) -> List[List[str]]:
    votesplat = str(BIN / "votesplat")
    given = ["--load-config", str(config)]
    return [
        [votesplat, "export", *given, "--output-dir", str(tmp_path / "export")],
        [votesplat, "click", *given, "--view", "0", "--x", "1", "--y", "1", "--output-dir", str(tmp_path / "click")],
        [votesplat, "query", *given, "mug", "--clip-random-init", "--clip-model", "ViT-S-32-alt"],
        [
            votesplat,
            "query-eval",
            *given,
            "--labels",
            str(labels),
            "--clip-random-init",
            "--clip-model",
            "ViT-S-32-alt",
        ],
        [votesplat, "eval", *given, "--output-dir", str(tmp_path / "eval")],
        [str(BIN / "ns-export"), "votesplat-instances", *given, "--output-dir", str(tmp_path / "export")],
    ]


@pytest.mark.parametrize("index", range(6), ids=["export", "click", "query", "query-eval", "eval", "ns-export"])
def test_every_command_refuses_a_crafted_config_in_one_line(index, tmp_path, run_console_script):
    marker = tmp_path / "ran"
    config = tmp_path / "evil" / "config.yml"
    config.parent.mkdir()
    config.write_text(APPLY_OS_SYSTEM.format(marker=marker) + "\n")
    labels = tmp_path / "evil" / "labels"  # query-eval reads them first
    write_scene_labels(DEMO_SCENE, labels)
    argv = commands(config, tmp_path, labels)[index]
    done = run_console_script(argv)
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr + done.stdout
    lines = [line for line in done.stderr.splitlines() if ": error: " in line]
    assert len(lines) == 1, done.stderr
    assert f"--load-config {config}: refused to load tag !!python/object/apply:os.system at line 1" in lines[0]
    assert not marker.exists()
    assert sorted(path.name for path in tmp_path.iterdir()) == ["evil"]  # nothing written


# ------------------------------------------------------------------ checkpoints
def test_retrofit_sources_that_are_no_checkpoint_are_refused_in_one_line(tmp_path):
    flag = "--pipeline.model.retrofit-from"
    marker = tmp_path / "ran"
    notes = tmp_path / "notes.txt"
    notes.write_text("not a checkpoint")
    with pytest.raises(VoteSplatInputError, match=f"{flag} {notes}: not a checkpoint"):
        latest_checkpoint(notes)
    with pytest.raises(VoteSplatInputError, match=f"{flag} {tmp_path / 'empty'}: no checkpoint found"):
        latest_checkpoint(tmp_path / "empty")
    garbage = tmp_path / "garbage.ckpt"
    garbage.write_bytes(b"<html>404</html>" * 50)
    payload = tmp_path / "payload.ckpt"
    torch.save({"step": 1, "pipeline": Payload(marker)}, payload)
    for path, reason in ((garbage, "it is not a PyTorch weights file"), (payload, "Python objects besides weights")):
        with pytest.raises(VoteSplatInputError) as error:
            load_gaussians(latest_checkpoint(path))
        message = str(error.value)
        assert message.startswith(f"{flag} {path} cannot be loaded: ") and reason in message, message
        assert "weights_only" not in message and "\n" not in message
    assert not marker.exists()


def test_a_run_whose_checkpoint_is_a_payload_is_refused_before_the_model_is_built(tmp_path):
    marker = tmp_path / "ran"
    config = votesplat_config(tmp_path / "outputs")
    config.save_config()
    checkpoint = config.get_checkpoint_dir() / "step-000000009.ckpt"
    checkpoint.parent.mkdir(parents=True)
    torch.save({"step": 9, "pipeline": Payload(marker)}, checkpoint)
    config_path = config.get_base_dir() / "config.yml"
    with pytest.raises(VoteSplatInputError) as error:
        load_run(config_path)
    assert str(error.value).startswith(f"checkpoint {checkpoint} (of --load-config {config_path}) cannot be loaded: ")
    assert "Python objects besides weights" in str(error.value) and "weights_only" not in str(error.value)
    assert not marker.exists()


def test_a_resumed_run_is_opened_from_its_own_checkpoints_not_those_it_resumed_from(tmp_path):
    from votesplat_ns.ns.run import check_run

    config = votesplat_config(tmp_path / "outputs")
    config.load_dir = tmp_path / "gone" / "nerfstudio_models"  # the first run, since deleted
    config.save_config()
    own = config.get_checkpoint_dir() / "step-000000004.ckpt"
    own.parent.mkdir(parents=True)
    save_resumable(own, 4)
    assert check_run(config.get_base_dir() / "config.yml") == own


def save_resumable(path: Path, step: int) -> None:
    torch.save({"step": step, "pipeline": {"_model.x": torch.zeros(2)}, "optimizers": {}, "scalers": {}}, path)


def test_resume_skips_a_half_written_newest_checkpoint_for_the_previous_one(tmp_path, capsys):
    for step in (100, 200, 300):
        save_resumable(tmp_path / f"step-{step:09d}.ckpt", step)
    data = (tmp_path / "step-000000300.ckpt").read_bytes()
    (tmp_path / "step-000000300.ckpt").write_bytes(data[: len(data) // 2])  # killed during the save
    (tmp_path / "step-000000400.ckpt").write_bytes(b"")  # killed before its first write
    (tmp_path / "notes.txt").write_text("nerfstudio's own listing fails on a file like this")
    found = resume_state(tmp_path, None, None)
    assert found is not None
    path, state = found
    assert path == tmp_path / "step-000000200.ckpt" and state["step"] == 200
    out = capsys.readouterr().out
    assert "skipping checkpoint" in out and "step-000000300.ckpt" in out and "step-000000400.ckpt" in out


def test_resume_refuses_a_payload_and_a_folder_without_a_good_checkpoint(tmp_path):
    marker = tmp_path / "ran"
    folder = tmp_path / "models"
    folder.mkdir()
    save_resumable(folder / "step-000000100.ckpt", 100)
    torch.save({"step": 200, "pipeline": Payload(marker)}, folder / "step-000000200.ckpt")
    with pytest.raises(VoteSplatInputError) as error:
        resume_state(folder, None, None)
    message = str(error.value)
    assert message.startswith(f"--load-dir {folder}: checkpoint {folder / 'step-000000200.ckpt'} cannot be loaded")
    assert "Python objects besides weights" in message and "weights_only" not in message
    with pytest.raises(VoteSplatInputError, match="--load-checkpoint .*Python objects besides weights"):
        resume_state(None, None, folder / "step-000000200.ckpt")
    assert not marker.exists()

    damaged = tmp_path / "damaged"
    damaged.mkdir()
    (damaged / "step-000000100.ckpt").write_bytes(b"PK\x03\x04" + b"\x00" * 64)
    with pytest.raises(VoteSplatInputError, match="truncated or damaged"):
        resume_state(damaged, None, None)
    with pytest.raises(VoteSplatInputError, match=f"--load-dir {tmp_path / 'none'}: no checkpoint there"):
        resume_state(tmp_path / "none", None, None)
    with pytest.raises(VoteSplatInputError, match="--load-step 7: no checkpoint there"):
        resume_state(folder, 7, None)
    assert resume_state(None, None, None) is None


@pytest.mark.parametrize("source", ["retrofit", "load-dir"])
def test_ns_train_refuses_a_payload_checkpoint_in_one_line(source, tmp_path, run_console_script):
    marker = tmp_path / "ran"
    models = tmp_path / "models"
    models.mkdir()
    torch.save({"step": 5, "pipeline": Payload(marker)}, models / "step-000000005.ckpt")
    flag = ["--pipeline.model.retrofit-from", str(models)] if source == "retrofit" else ["--load-dir", str(models)]
    argv = [
        str(BIN / "ns-train"),
        "votesplat",
        "--data",
        str(DEMO_SCENE),
        "--vis",
        "tensorboard",
        "--max-num-iterations",
        "1",
        "--output-dir",
        str(tmp_path / "runs"),
        "--machine.device-type",
        "cpu",
        "--pipeline.datamanager.cache-dir",
        str(tmp_path / "cache"),
        *flag,
    ]
    done = run_console_script(argv)
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr + done.stdout
    lines = [line for line in done.stderr.splitlines() if ": error: " in line]
    assert len(lines) == 1 and lines[0].startswith(f"ns-train votesplat: error: {flag[0]} "), done.stderr
    assert "Python objects besides weights" in lines[0] and "weights_only" not in lines[0]
    assert not marker.exists()


def test_ns_train_resumes_a_real_checkpoint_past_a_half_written_newer_one(tmp_path, capsys):
    from votesplat_ns.ns.method import setup_trainer_in_process
    from votesplat_ns.ns.trainer import VoteSplatTrainer

    first = setup_trainer_in_process(DEMO_SCENE, tmp_path, 1, 0, "cpu", "first")
    assert isinstance(first, VoteSplatTrainer)
    first.pipeline.model.gauss_params["means"].data += 1.0  # unlike any fresh start
    first.save_checkpoint(7)  # what a run writes every --steps-per-save steps (no training needed for a real file)
    models = first.config.get_checkpoint_dir()
    saved = first.pipeline.model.gauss_params["means"].detach().clone()
    save_resumable(models / "step-000000009.ckpt", 9)
    data = (models / "step-000000009.ckpt").read_bytes()
    (models / "step-000000009.ckpt").write_bytes(data[: len(data) // 3])  # killed during the save

    resumed = setup_trainer_in_process(DEMO_SCENE, tmp_path, 1, 0, "cpu", "resumed", load_dir=models)
    assert resumed._start_step == 8
    assert torch.equal(resumed.pipeline.model.gauss_params["means"].detach(), saved)
    assert "skipping checkpoint" in capsys.readouterr().out
