"""Voting leaves the colour training as it is: with the same seed, a run that votes on every step ends with
the same Gaussians (bitwise, on CPU) as one that never votes, through densification. The vote losses reach
only the offsets, and the vote pixels are drawn from their own random stream, so splatfacto's draws (random
backgrounds, densification's split samples) stay those of a run without votes. And with splatfacto's
multi-tensor Adam for the Gaussians' groups, those Gaussians are nerfstudio's own splatfacto's."""

from __future__ import annotations

import copy
import dataclasses

import torch
from conftest import DEMO_SCENE
from nerfstudio.models.splatfacto import SplatfactoModel
from test_resume import BUDGET, make_trainer

from votesplat_ns.ns.compat import MetricAtFirstUse
from votesplat_ns.ns.method import setup_trainer, trainer_config_in_process
from votesplat_ns.ns.model import SPLAT_PARAM_NAMES
from votesplat_ns.ns.patches import (
    cuda_calls_stay_on_cpu,
    install_rasterizer_in_splatfacto,
    splatfacto_metrics_at_first_use,
)

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


def splatfacto_like(config):
    """nerfstudio's own splatfacto method config (its model, datamanager and optimizers), with votesplat's
    ``config``'s run settings and the values of every model and datamanager field the two methods share."""
    from nerfstudio.configs.method_configs import method_configs

    twin = copy.deepcopy(method_configs["splatfacto"])
    for name in ("machine", "vis", "output_dir", "timestamp", "data", "load_dir", "max_num_iterations"):
        setattr(twin, name, copy.deepcopy(getattr(config, name)))
    for name in ("steps_per_eval_image", "steps_per_eval_all_images", "steps_per_save"):
        setattr(twin, name, getattr(config, name))
    for part in ("model", "datamanager"):
        ours, theirs = getattr(config.pipeline, part), getattr(twin.pipeline, part)
        for field in dataclasses.fields(theirs):
            if field.name != "_target":
                setattr(theirs, field.name, copy.deepcopy(getattr(ours, field.name)))
    return twin


def test_without_votes_and_with_splatfactos_adam_it_trains_splatfactos_gaussians(tmp_path):
    """The only difference left between votesplat's colour training and splatfacto's is the fused Adam step of the
    Gaussians' groups (the same update up to rounding): with ``fused`` False, a run that votes only on its last step
    (after that step's colour draws) ends with nerfstudio's splatfacto's Gaussians, bitwise, through densification.
    So a PSNR difference between the two methods on a GPU is that rounding and gsplat's atomic adds, nothing else."""
    config = trainer_config_in_process(DEMO_SCENE, tmp_path, STEPS, STEPS - 1, "cpu", "run", **BUDGET)
    for name in SPLAT_PARAM_NAMES:
        config.optimizers[name]["optimizer"].fused = False
    runs, initial_counts = {}, {}
    # splatfacto on CPU as votesplat runs it: its hard-coded .cuda() calls kept on the CPU, LPIPS offline and the
    # rasterizer of ns/rasterizer.py (gsplat's own is CUDA-only; on CUDA that one calls gsplat's)
    install_rasterizer_in_splatfacto()
    populate_modules = SplatfactoModel.populate_modules
    with cuda_calls_stay_on_cpu(model_on_cpu=True), splatfacto_metrics_at_first_use():
        for method, method_config in (("splatfacto", splatfacto_like(config)), ("votesplat", config)):
            trainer = setup_trainer(method_config)
            assert trainer.config.method_name == method
            trainer.pipeline.model.strategy.pause_refine_after_reset = 0  # as make_trainer: densify in a short run
            initial_counts[method] = trainer.pipeline.model.num_points
            trainer.train()
            model = trainer.pipeline.model
            runs[method] = {name: model.gauss_params[name].detach().clone() for name in SPLAT_PARAM_NAMES}
            assert isinstance(model.psnr, MetricAtFirstUse) and model.psnr.built is not None  # built by training
    assert SplatfactoModel.populate_modules is populate_modules  # the block's wrapper is gone with it
    assert runs["splatfacto"]["means"].shape[0] != initial_counts["splatfacto"]  # the runs densified
    for name in SPLAT_PARAM_NAMES:
        assert torch.equal(runs["votesplat"][name], runs["splatfacto"][name]), name
