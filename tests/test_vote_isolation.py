"""Voting leaves the colour training as it is: with the same seed, a run that votes on every step ends with
the same Gaussians (bitwise, on CPU) as one that never votes, through densification. The vote losses reach
only the offsets, and the vote pixels are drawn from their own random stream, so splatfacto's draws (random
backgrounds, densification's split samples) stay those of a run without votes."""

from __future__ import annotations

import torch
from conftest import DEMO_SCENE

from votesplat_ns.ns.method import setup_trainer_in_process
from votesplat_ns.ns.model import SPLAT_PARAM_NAMES

STEPS = 22  # densifies at steps 10 and 20
# CPU budget: 1/4 resolution (32 px), 256 vote pixels per step, densify every 10 steps from step 10
BUDGET = dict(
    num_downscales=2,
    resolution_schedule=100_000,
    vote_pixels_per_step=256,
    vote_every_n_steps=1,
    warmup_length=10,
    refine_every=10,
    foreground_min_masked_share=None,
)


def train(output_dir, name: str, vote_start: int) -> dict:
    trainer = setup_trainer_in_process(DEMO_SCENE, output_dir, STEPS, vote_start, "cpu", name, **BUDGET)
    # a run this short densifies only without splatfacto's pause after the step-0 opacity reset
    trainer.pipeline.model.strategy.pause_refine_after_reset = 0
    initial_count = trainer.pipeline.model.num_points
    trainer.train()
    params = {name: param.detach().clone() for name, param in trainer.pipeline.model.gauss_params.items()}
    return {"params": params, "initial_count": initial_count}


def test_votes_leave_the_colour_training_unchanged(tmp_path):
    voting = train(tmp_path, "voting", vote_start=0)
    # votes on its last step only (a run must vote): its draws come after that step's colour draws
    silent = train(tmp_path, "silent", vote_start=STEPS - 1)
    assert voting["params"]["means"].shape[0] != voting["initial_count"]  # the runs densified
    assert not torch.equal(voting["params"]["vote_offsets"], silent["params"]["vote_offsets"])
    for name in SPLAT_PARAM_NAMES:
        assert torch.equal(voting["params"][name], silent["params"][name]), name
