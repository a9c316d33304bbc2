"""Every preset in configs/ is a valid set of ns-train votesplat flags."""

from pathlib import Path

import pytest
import tyro
from nerfstudio.engine.trainer import TrainerConfig

from votesplat_ns.ns.method import votesplat_trainer_config

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


def test_vote_step_schedule():
    from votesplat_ns.ns.model import vote_step_due

    assert [step for step in range(10) if vote_step_due(step, 3, 1)] == [3, 4, 5, 6, 7, 8, 9]
    assert [step for step in range(12) if vote_step_due(step, 3, 4)] == [3, 7, 11]
    with pytest.raises(ValueError, match="vote_every_n_steps"):
        vote_step_due(5, 0, 0)
