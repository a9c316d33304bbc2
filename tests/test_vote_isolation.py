"""Voting leaves the colour training as it is: with the same seed, a run that votes on every step ends with
the same Gaussians (bitwise, on CPU) as one that never votes, through densification. The vote losses reach
only the offsets, and the vote pixels are drawn from their own random stream, so splatfacto's draws (random
backgrounds, densification's split samples) stay those of a run without votes."""

from __future__ import annotations

import torch
from test_resume import make_trainer

from votesplat_ns.ns.model import SPLAT_PARAM_NAMES

STEPS = 22  # densifies at steps 10 and 20


def train(output_dir, name: str, vote_start: int) -> dict:
    trainer = make_trainer(output_dir, STEPS, name, vote_start=vote_start)
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

    # the vote stream is seeded with the run's seed: the same run again draws the same pixels, so the same
    # Gaussians vote at every step (equal support counts); the offsets agree up to the order of torch's
    # multi-threaded CPU sums (bitwise with one thread)
    again = train(tmp_path, "voting_again", vote_start=0)
    assert torch.equal(again["params"]["vote_support"], voting["params"]["vote_support"])
    torch.testing.assert_close(again["params"]["vote_offsets"], voting["params"]["vote_offsets"], rtol=0, atol=1e-6)
