"""The one-line error path (votesplat_ns/errors.py) and the dataset checks, in process (issue #2); commands: test_bad_inputs.py."""

from __future__ import annotations

import errno
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from votesplat_ns import errors
from votesplat_ns.errors import (
    VoteSplatInputError,
    check_device_available,
    check_writable_folder,
    input_error_for_write,
    install_excepthook,
    load_failure_reason,
    one_line_errors,
    one_line_message,
    writing_into,
)
from votesplat_ns.ns.datamanager import VoteDataManagerConfig, check_data_input, check_vote_schedule

DEMO_SCENE = Path(__file__).resolve().parents[1] / "votesplat_ns" / "data" / "demo"


# The ns-train subprocess cases (missing data, no transforms.json, missing images, CUDA) are in the
# bad-input catalogue, tests/test_bad_inputs.py.


# ------------------------------------------------------------------ in-process
@pytest.fixture
def restore_excepthook():
    original = sys.excepthook
    yield
    sys.excepthook = original


def test_excepthook_shortens_only_input_errors(restore_excepthook, capsys, monkeypatch):
    seen = []
    sys.excepthook = lambda *args: seen.append(args)
    install_excepthook()
    install_excepthook()  # idempotent: one wrapper
    assert sys.excepthook.previous is not None and not getattr(
        sys.excepthook.previous, "_votesplat_input_errors", False
    )
    monkeypatch.setattr(sys, "argv", ["/venv/bin/ns-train", "votesplat", "--data", "x"])

    error = VoteSplatInputError("first line\n  second line")
    sys.excepthook(VoteSplatInputError, error, None)
    assert capsys.readouterr().err == "ns-train votesplat: error: first line; second line\n"
    assert seen == []

    for other in (
        ValueError("plain"),
        FileNotFoundError(2, "No such file", "x"),
        RuntimeError("bug"),
        KeyboardInterrupt(),
    ):
        sys.excepthook(type(other), other, None)
        assert seen[-1][1] is other
    assert len(seen) == 4
    assert capsys.readouterr().err == ""


def test_program_name():
    assert errors.program_name(["/v/bin/ns-train", "votesplat", "--data", "x"]) == "ns-train votesplat"
    assert errors.program_name(["/v/bin/ns-viewer", "--load-config", "c.yml"]) == "ns-viewer"
    assert (
        errors.program_name(["/v/bin/ns-export", "votesplat-instances", "--load-config", "c"])
        == "ns-export votesplat-instances"
    )
    assert errors.program_name(["/v/bin/ns-export", "gaussian-splat"]) == "ns-export"
    assert errors.program_name(["/v/bin/votesplat", "click", "--view", "1"]) == "votesplat click"
    assert errors.program_name(["pytest"]) == "votesplat"
    assert one_line_message(VoteSplatInputError(""), ["ns-eval"]) == "ns-eval: error: VoteSplatInputError"
    assert one_line_message(ValueError("a\nb"), prog="votesplat query") == "votesplat query: error: a; b"


def test_one_line_errors_catches_only_what_it_is_told(capsys):
    with pytest.raises(SystemExit) as exit_info:
        with one_line_errors(catch=(ValueError,), prog="votesplat masks"):
            raise ValueError("--preview must be >= 0\n  got -1")
    assert exit_info.value.code == 1
    assert capsys.readouterr().err == "votesplat masks: error: --preview must be >= 0; got -1\n"
    with pytest.raises(RuntimeError, match="a bug"):
        with one_line_errors(prog="votesplat masks"):
            raise RuntimeError("a bug")
    with pytest.raises(ValueError):  # only VoteSplatInputError by default
        with one_line_errors(prog="votesplat masks"):
            raise ValueError("not ours")


def test_writable_folder_check(tmp_path, monkeypatch):
    check_writable_folder(tmp_path / "new" / "deeper", "--output-dir")  # created later: its parent is writable
    assert not (tmp_path / "new").exists()  # the check writes nothing
    (tmp_path / "file").write_text("x")
    with pytest.raises(VoteSplatInputError, match=r"^--output-dir .*file/sub: .*file is a file, not a folder"):
        check_writable_folder(tmp_path / "file" / "sub", "--output-dir")
    # os.access answers for this process: refuse where it says no (root may write anywhere, so simulate it)
    monkeypatch.setattr(errors.os, "access", lambda path, mode: Path(path) != tmp_path)
    with pytest.raises(
        VoteSplatInputError, match=rf"^--cache-dir {tmp_path}/c: cannot write in {tmp_path} \(permission denied"
    ):
        check_writable_folder(tmp_path / "c", "--cache-dir")
    with pytest.raises(VoteSplatInputError, match=r"^--output-dir out/x: cannot write in"):
        check_writable_folder(tmp_path / "x", "--output-dir", given="out/x")


def test_write_errors_become_input_errors_only_for_the_folder(tmp_path):
    denied = PermissionError(errno.EACCES, "Permission denied", str(tmp_path / "cache" / "entry" / "config.json"))
    error = input_error_for_write(denied, tmp_path / "cache", "--cache-dir")
    assert str(error) == (
        f"--cache-dir {tmp_path / 'cache'}: cannot write {tmp_path / 'cache' / 'entry' / 'config.json'} (Permission denied); "
        "make it writable or choose another --cache-dir"
    )
    assert (
        input_error_for_write(PermissionError(errno.EACCES, "x", str(tmp_path / "elsewhere")), tmp_path / "cache", "f")
        is None
    )
    assert (
        input_error_for_write(
            FileNotFoundError(errno.ENOENT, "x", str(tmp_path / "cache" / "a")), tmp_path / "cache", "f"
        )
        is None
    )
    assert input_error_for_write(PermissionError(errno.EACCES, "no file name"), tmp_path / "cache", "f") is None
    assert (
        input_error_for_write(OSError(errno.EROFS, "Read-only file system", str(tmp_path)), tmp_path / "cache", "f")
        is not None
    )
    with pytest.raises(VoteSplatInputError, match="No space left"):
        with writing_into(tmp_path / "cache", "--cache-dir"):
            raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "cache" / "x.npy"))
    with pytest.raises(PermissionError):
        with writing_into(tmp_path / "cache", "--cache-dir"):
            raise denied.__class__(errno.EACCES, "Permission denied", "/etc/shadow")


def test_load_failure_reasons_never_relay_torch_advice(tmp_path):
    garbage = tmp_path / "weights.bin"
    garbage.write_bytes(b"<html>not found</html>" * 10)
    with pytest.raises(Exception) as error:
        torch.load(garbage, map_location="cpu")
    assert load_failure_reason(error.value) == "it is not a PyTorch weights file"
    torch.save({"w": torch.zeros(100)}, tmp_path / "good.pt")
    data = (tmp_path / "good.pt").read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(Exception) as error:
        torch.load(tmp_path / "cut.pt", map_location="cpu")
    assert load_failure_reason(error.value) == "the file is truncated or damaged"
    model = torch.nn.Linear(2, 2)
    with pytest.raises(Exception) as error:
        model.load_state_dict({"weight": torch.zeros(3, 3)})
    assert load_failure_reason(error.value) == "it holds weights of another model"
    assert "weights_only" not in load_failure_reason(RuntimeError("Weights only load failed ... weights_only=False"))


@pytest.mark.parametrize(
    "start, every, start_step, steps, ok",
    [
        (500, 4, 0, 30000, True),
        (500, 4, 0, 500, False),  # steps 0..499
        (500, 4, 0, 501, True),  # step 500 votes
        (0, 1, 0, 1, True),
        (5, 4, 20, 1, False),  # resumed at step 20: 5, 9, ..., 21 vote, 20 does not
        (5, 4, 20, 2, True),
        (5, 4, 21, 1, True),
    ],
)
def test_vote_schedule(start, every, start_step, steps, ok):
    config = SimpleNamespace(
        vote_start_step=start, vote_every_n_steps=every, vote_loss_weight=1.0, distortion_loss_weight=0.1
    )
    model = SimpleNamespace(vote_only=False, config=config)
    if ok:
        check_vote_schedule(model, start_step, steps)
    else:
        with pytest.raises(
            VoteSplatInputError, match=rf"^--pipeline.model.vote-start-step {start} is past the last training step"
        ):
            check_vote_schedule(model, start_step, steps)
    check_vote_schedule(
        SimpleNamespace(vote_only=True, config=model.config), start_step, steps
    )  # a retrofit votes every step
    votes_off = SimpleNamespace(**{**vars(config), "vote_loss_weight": 0.0, "distortion_loss_weight": 0.0})
    check_vote_schedule(SimpleNamespace(vote_only=False, config=votes_off), start_step, steps)  # no votes, on purpose


def test_input_error_is_a_value_error():
    with pytest.raises(ValueError):
        raise VoteSplatInputError("x")


def test_device_check(monkeypatch):
    check_device_available("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(VoteSplatInputError, match="--machine.device-type cpu"):
        check_device_available("cuda:0")
    with pytest.raises(VoteSplatInputError, match="--machine.device-type cpu"):
        check_device_available(torch.device("cuda"))
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    with pytest.raises(VoteSplatInputError, match="MPS"):
        check_device_available("mps")
    with pytest.raises(VoteSplatInputError, match="'gpu0' is not a device"):
        check_device_available("gpu0")


def config_for(data: Path, **dataparser) -> VoteDataManagerConfig:
    config = VoteDataManagerConfig(data=data)
    for name, value in dataparser.items():
        setattr(config.dataparser, name, value)
    return config


def test_data_checks_in_process(tmp_path):
    check_data_input(config_for(DEMO_SCENE))
    check_data_input(config_for(DEMO_SCENE / "transforms.json"))

    with pytest.raises(VoteSplatInputError, match=r"file not found"):
        check_data_input(config_for(tmp_path / "missing" / "transforms.json"))
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(VoteSplatInputError, match=r"is a file, not a dataset"):
        check_data_input(config_for(tmp_path / "notes.txt"))

    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "transforms.json").write_text('{"frames": [')
    with pytest.raises(VoteSplatInputError, match=r"transforms.json is not valid JSON \(.*line 1"):
        check_data_input(config_for(broken))
    (broken / "transforms.json").write_text('{"frames": []}')
    with pytest.raises(VoteSplatInputError, match=r"lists no frames"):
        check_data_input(config_for(broken))

    # images checked where nerfstudio reads them: images_N/ with --downscale-factor N; not at all for inference
    scene = tmp_path / "scene"
    shutil.copytree(DEMO_SCENE / "images", scene / "images")
    shutil.copy(DEMO_SCENE / "transforms.json", scene / "transforms.json")
    check_data_input(config_for(scene))
    with pytest.raises(VoteSplatInputError, match=r"images_2/ \(--downscale-factor 2\)"):
        check_data_input(config_for(scene, downscale_factor=2))
    (scene / "images" / "frame_00003.png").unlink()
    with pytest.raises(VoteSplatInputError, match=r"1 of \d+ images .* \(first: .*frame_00003\.png\)"):
        check_data_input(config_for(scene))
    check_data_input(config_for(scene), check_images=False)


def test_file_missing_while_nerfstudio_parses_becomes_one_line(monkeypatch):
    from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager

    def parse(self, *args, **kwargs):
        raise FileNotFoundError(2, "No such file or directory", "scene/sparse/0/cameras.bin")

    monkeypatch.setattr(FullImageDatamanager, "__init__", parse)
    with pytest.raises(
        VoteSplatInputError, match=r"^--data .*demo: scene/sparse/0/cameras.bin not found; check that the dataset"
    ):
        config_for(DEMO_SCENE).setup(device="cpu", test_mode="val")

    def bug(self, *args, **kwargs):
        raise FileNotFoundError("no filename: a bug, not input")

    monkeypatch.setattr(FullImageDatamanager, "__init__", bug)
    with pytest.raises(FileNotFoundError, match="a bug"):
        config_for(DEMO_SCENE).setup(device="cpu", test_mode="val")
