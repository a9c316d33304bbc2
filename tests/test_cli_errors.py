"""Bad input to ns-train votesplat ends with one actionable line on stderr, not a traceback (issue #2)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from votesplat_ns import cli_errors
from votesplat_ns.cli_errors import VoteSplatInputError, check_device_available, install_excepthook, one_line_message
from votesplat_ns.datamanager import VoteDataManagerConfig, check_data_input

DEMO_SCENE = Path(__file__).resolve().parents[1] / "votesplat_ns" / "data" / "demo"
NS_TRAIN = Path(sys.executable).parent / "ns-train"
PREFIX = "ns-train votesplat: error: "


def ns_train(data: Path, tmp_path: Path, device: str = "cpu") -> subprocess.CompletedProcess:
    command = [
        str(NS_TRAIN), "votesplat", "--data", str(data), "--vis", "tensorboard", "--max-num-iterations", "1",
        "--output-dir", str(tmp_path / "runs"), "--machine.device-type", device,
    ]
    return subprocess.run(command, capture_output=True, text=True, cwd=tmp_path, timeout=600, env=dict(os.environ, COLUMNS="200"))


def assert_one_line_error(result: subprocess.CompletedProcess, *needles: str) -> str:
    assert result.returncode != 0, result.stdout[-2000:]
    assert "Traceback" not in result.stderr, result.stderr[-4000:]
    last = [line for line in result.stderr.splitlines() if line.strip()][-1]
    assert last.startswith(PREFIX), result.stderr[-4000:]
    for needle in needles:
        assert needle in last, last
    return last


def demo_transforms_without_images(folder: Path) -> Path:
    folder.mkdir()
    shutil.copy(DEMO_SCENE / "transforms.json", folder / "transforms.json")
    return folder


# ------------------------------------------------------------------ ns-train subprocesses (~15 s each)
def test_missing_data_folder(tmp_path):
    result = ns_train(tmp_path / "nonexistent", tmp_path)
    assert_one_line_error(result, f"--data {tmp_path / 'nonexistent'}: folder not found", "transforms.json", "ns-process-data")


def test_folder_without_transforms_json(tmp_path):
    (tmp_path / "photos").mkdir()
    result = ns_train(tmp_path / "photos", tmp_path)
    assert_one_line_error(result, "this folder holds no transforms.json", "ns-process-data")


def test_transforms_json_whose_images_are_missing(tmp_path):
    data = demo_transforms_without_images(tmp_path / "scene")
    frames = len(json.loads((data / "transforms.json").read_text())["frames"])
    result = ns_train(data, tmp_path)
    assert_one_line_error(
        result, f"{frames} of {frames} images listed in transforms.json are missing", f"(first: {data / 'images' / 'frame_00001.png'})"
    )


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here, so --machine.device-type cuda is valid input")
def test_cuda_requested_without_cuda(tmp_path):
    result = ns_train(DEMO_SCENE, tmp_path, device="cuda")
    assert_one_line_error(result, "CUDA is not available on this machine", "--machine.device-type cpu")


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
    assert sys.excepthook.previous is not None and not getattr(sys.excepthook.previous, "_votesplat_input_errors", False)
    monkeypatch.setattr(sys, "argv", ["/venv/bin/ns-train", "votesplat", "--data", "x"])

    error = VoteSplatInputError("first line\n  second line")
    sys.excepthook(VoteSplatInputError, error, None)
    assert capsys.readouterr().err == "ns-train votesplat: error: first line; second line\n"
    assert seen == []

    for other in (ValueError("plain"), FileNotFoundError(2, "No such file", "x"), RuntimeError("bug"), KeyboardInterrupt()):
        sys.excepthook(type(other), other, None)
        assert seen[-1][1] is other
    assert len(seen) == 4
    assert capsys.readouterr().err == ""


def test_program_name():
    assert cli_errors.program_name(["/v/bin/ns-train", "votesplat", "--data", "x"]) == "ns-train votesplat"
    assert cli_errors.program_name(["/v/bin/ns-viewer", "--load-config", "c.yml"]) == "ns-viewer"
    assert cli_errors.program_name(["pytest"]) == "votesplat"
    assert one_line_message(VoteSplatInputError(""), ["ns-eval"]) == "ns-eval: error: VoteSplatInputError"


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
    with pytest.raises(VoteSplatInputError, match=r"^--data .*demo: scene/sparse/0/cameras.bin not found; check that the dataset"):
        config_for(DEMO_SCENE).setup(device="cpu", test_mode="val")

    def bug(self, *args, **kwargs):
        raise FileNotFoundError("no filename: a bug, not input")

    monkeypatch.setattr(FullImageDatamanager, "__init__", bug)
    with pytest.raises(FileNotFoundError, match="a bug"):
        config_for(DEMO_SCENE).setup(device="cpu", test_mode="val")
