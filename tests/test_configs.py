"""Every preset in configs/ is a valid set of ns-train votesplat flags."""

from pathlib import Path

import pytest
import tyro
from nerfstudio.engine.trainer import TrainerConfig

from votesplat_ns.method import votesplat_trainer_config

PRESETS = sorted((Path(__file__).resolve().parents[1] / "configs").glob("*.args"))


def preset_args(path: Path):
    return [word for line in path.read_text().splitlines() if not line.startswith("#") for word in line.split()]


def test_presets_exist():
    assert {p.stem for p in PRESETS} >= {"360", "forward-facing", "small-objects"}


@pytest.mark.parametrize("path", PRESETS, ids=lambda p: p.stem)
def test_preset_parses_and_sets_the_model(path):
    config = tyro.cli(TrainerConfig, default=votesplat_trainer_config(), args=preset_args(path))
    model = config.pipeline.model
    expected = dict(zip(preset_args(path)[::2], preset_args(path)[1::2]))
    assert model.distortion_loss_weight == float(expected["--pipeline.model.distortion-loss-weight"])
    assert model.vote_loss_weight == float(expected["--pipeline.model.vote-loss-weight"])
