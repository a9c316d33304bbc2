"""Retrofit: add instances to a trained scene by training only the offsets (the vote-only path)."""

from __future__ import annotations

import pytest
import torch
from conftest import DEMO_SCENE, assert_offsets_beat_zero, train_votesplat
from nerfstudio.utils.eval_utils import eval_setup

from votesplat_ns.ns import vote_init
from votesplat_ns.ns.run import SPLAT_PARAM_NAMES, latest_checkpoint, load_gaussians
from votesplat_ns.ns.vote_init import lifted_offsets


@pytest.fixture(scope="module")
def splatfacto_checkpoint(trained_demo, tmp_path_factory):
    """A checkpoint with splatfacto's structure: the demo run's, minus everything VoteSplat added."""
    state = torch.load(latest_checkpoint(trained_demo.parent), map_location="cpu")
    state["pipeline"] = {k: v for k, v in state["pipeline"].items() if "vote_" not in k}
    path = tmp_path_factory.mktemp("splatfacto") / "step-000000100.ckpt"
    torch.save(state, path)
    return path


def test_retrofit_trains_only_the_offsets(splatfacto_checkpoint, tmp_path):
    # 30 steps, as test_retrofit_ply.py's retrofits: every level supervised, offsets that beat zero
    config_path = train_votesplat(
        DEMO_SCENE, tmp_path, steps=30, vote_start=0, retrofit_from=splatfacto_checkpoint, vote_pixels_per_step=1024
    )
    _, pipeline, _, _ = eval_setup(config_path, test_mode="val")
    model = pipeline.model
    source = load_gaussians(splatfacto_checkpoint)
    for name in SPLAT_PARAM_NAMES:  # geometry and appearance untouched, no densification
        assert torch.equal(model.gauss_params[name].data.cpu(), source[name]), name
    offsets = model.gauss_params["vote_offsets"].data
    support = model.gauss_params["vote_support"].data
    assert (support > 0).any(dim=0).all(), "every level must have received vote supervision"
    for level in range(offsets.shape[1]):
        assert offsets[support[:, level] > 0, level].abs().sum() > 0
        assert offsets[support[:, level] == 0, level].abs().max() == 0

    assert_offsets_beat_zero(pipeline)


def test_retrofit_can_start_from_the_lifted_mask_centroids(splatfacto_checkpoint, tmp_path, monkeypatch):
    # the lifted start the retrofit computes (one render per mask view: kept, not computed a second time)
    lifted = []

    def recorded(*args, **kwargs):
        lifted.append(lifted_offsets(*args, **kwargs))
        return lifted[-1]

    monkeypatch.setattr(vote_init, "lifted_offsets", recorded)
    # vote losses weighted 0: the steps leave the offsets where the lifted start put them
    config_path = train_votesplat(
        DEMO_SCENE,
        tmp_path,
        steps=2,
        vote_start=0,
        retrofit_from=splatfacto_checkpoint,
        retrofit_init="lifted",
        vote_loss_weight=0.0,
        distortion_loss_weight=0.0,
        vote_pixels_per_step=256,
    )
    _, pipeline, _, _ = eval_setup(config_path, test_mode="val")
    model = pipeline.model
    offsets = model.gauss_params["vote_offsets"].data
    support = model.gauss_params["vote_support"].data
    (expected,) = lifted
    assert torch.allclose(offsets, expected.offsets.to(offsets.device), atol=1e-6)
    seen = expected.views > 0
    assert seen.any(dim=0).all(), "every level must have Gaussians seen in a mask"
    assert (offsets.norm(dim=-1)[seen] > 0).float().mean() > 0.99 and (offsets[~seen] == 0).all()
    # a Gaussian given a lifted vote counts as supervised (before the end-of-training mask share)
    assert torch.equal(support.abs(), expected.views.to(support.dtype))
    # the start alone already renders better votes than zero offsets
    assert_offsets_beat_zero(pipeline)


def test_retrofit_from_a_checkpoint_of_the_wrong_structure_is_a_clear_error(tmp_path):
    bad = tmp_path / "step-000000001.ckpt"
    torch.save({"step": 1, "pipeline": {"_model.field.weight": torch.zeros(3)}}, bad)
    with pytest.raises(ValueError, match="not a splatfacto checkpoint"):
        load_gaussians(bad)
    with pytest.raises(ValueError, match="no checkpoint found"):
        latest_checkpoint(tmp_path / "empty_run")
