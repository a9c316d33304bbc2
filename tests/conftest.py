"""Shared fixtures: one short CPU training run of votesplat on the bundled demo scene."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

DEMO_SCENE = Path(__file__).resolve().parents[1] / "votesplat_ns" / "data" / "demo"
# Short enough for CI on 2 cores, long enough for the votes to move well past their start.
DEMO_STEPS = int(os.environ.get("VOTESPLAT_TEST_STEPS", "240"))
DEMO_VOTE_START = 40


def train_votesplat(data: Path, output_dir: Path, steps: int, vote_start: int, **model_overrides) -> Path:
    """Train votesplat in-process on CPU and return the run's config.yml."""
    from votesplat_ns.method import votesplat_trainer_config

    config = votesplat_trainer_config()
    config.machine.device_type = "cpu"
    config.vis = "tensorboard"
    config.output_dir = output_dir
    config.timestamp = "test"
    config.max_num_iterations = steps
    config.steps_per_eval_image = 10 * steps
    config.steps_per_eval_all_images = 10 * steps
    config.steps_per_save = 10 * steps
    config.data = data
    config.pipeline.datamanager.data = data
    config.pipeline.datamanager.cache_dir = output_dir / "vote_cache"
    model = config.pipeline.model
    model.vote_start_step = vote_start
    # CPU budget: render at 64 px (splatfacto's resolution schedule stays at 1/2 for the whole
    # run) and sample 1024 vote pixels per level; the vote loss is a mean over masked pixels,
    # so fewer samples keep its expected gradient.
    model.num_downscales = 1
    model.resolution_schedule = 100 * steps
    model.vote_pixels_per_step = 1024
    model.vote_every_n_steps = 1  # a few hundred CPU steps: every one counts
    for name, value in model_overrides.items():
        setattr(model, name, value)
    config.set_timestamp()
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    return config.get_base_dir() / "config.yml"


@pytest.fixture(scope="session")
def trained_demo(tmp_path_factory) -> Path:
    """config.yml of a votesplat run on the bundled demo scene (CPU, a few hundred steps).

    VOTESPLAT_TRAINED_DEMO=<config.yml of an earlier run of this fixture> reuses that run
    (a local shortcut while iterating on tests; CI always trains).
    """
    reuse = os.environ.get("VOTESPLAT_TRAINED_DEMO")
    if reuse:
        return Path(reuse)
    output_dir = tmp_path_factory.mktemp("demo_run")
    return train_votesplat(DEMO_SCENE, output_dir, DEMO_STEPS, DEMO_VOTE_START)
