"""A retrofit on two processes (torch.distributed over gloo, on the CPU): each rank votes on its own views, the
offsets' gradients are averaged before each step, and the offsets equal those of one process that takes the same
two views per step and averages their gradients the same way."""

from __future__ import annotations

import math
import os
import socket
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
from conftest import DEMO_SCENE

from votesplat_ns.errors import VoteSplatInputError
from votesplat_ns.ns.data_parallel import DataParallelOptimizers, training_ranks
from votesplat_ns.ns.method import setup_trainer_in_process, trainer_config_in_process
from votesplat_ns.ns.run import load_gaussians

STEPS = 3
SEED = 7
RANKS = 2


@pytest.fixture(scope="module")
def retrofit_source(tmp_path_factory) -> Path:
    """A splatfacto-shaped checkpoint: a Gaussian at each of the demo's sparse points (the dataparser's frame)."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    parser = NerfstudioDataParserConfig(data=DEMO_SCENE, load_3D_points=True).setup()
    metadata = parser.get_dataparser_outputs(split="train").metadata
    means = metadata["points3D_xyz"].float()
    colours = metadata["points3D_rgb"].float() / 255.0
    n = means.shape[0]
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    params = {
        "means": means,
        "scales": torch.full((n, 3), math.log(0.02)),
        "quats": quats,
        "features_dc": (colours - 0.5) / 0.28209479177387814,
        "features_rest": torch.zeros(n, 15, 3),
        "opacities": torch.full((n, 1), 2.0),
    }
    path = tmp_path_factory.mktemp("scene") / "step-000000000.ckpt"
    torch.save({"step": 0, "pipeline": {f"_model.gauss_params.{k}": v for k, v in params.items()}}, path)
    return path


def retrofit_config(output_dir: Path, source: Path, cache: Path):
    """Three vote-only steps of a retrofit of ``source``, at half resolution, 512 vote pixels a step."""
    return trainer_config_in_process(
        DEMO_SCENE,
        output_dir,
        STEPS,
        0,
        "cpu",
        "run",
        seed=SEED,
        datamanager_overrides={"cache_dir": cache},
        retrofit_from=source,
        num_downscales=1,
        resolution_schedule=100 * STEPS,
        vote_pixels_per_step=512,
        foreground_min_masked_share=None,
    )


def _rank(local_rank: int, init_file: str, config, result: str) -> None:
    """One rank, as nerfstudio's launch runs it (its _distributed_worker, then train_loop), over gloo."""
    from nerfstudio.scripts.train import _set_random_seed

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=local_rank, world_size=RANKS)
    try:
        _set_random_seed(config.machine.seed + local_rank)  # train_loop's seeding
        trainer = config.setup(local_rank=local_rank, world_size=RANKS)
        trainer.setup()
        assert isinstance(trainer.optimizers, DataParallelOptimizers)
        manager = trainer.pipeline.datamanager
        assert manager.view_shard == (local_rank, RANKS)
        assert all(index % RANKS == local_rank for index in manager.train_unseen_cameras)
        trainer.train()
        params = trainer.pipeline.model.gauss_params
        torch.save(
            {name: params[name].detach().clone() for name in ("vote_offsets", "vote_support")}, f"{result}.{local_rank}"
        )
    finally:
        dist.destroy_process_group()


def one_process_two_views_a_step(config) -> torch.Tensor:
    """The offsets after STEPS steps of one process that takes, per step, rank 0's and rank 1's view (each with
    the vote pixels that rank draws) and steps on the mean of their gradients."""
    trainer = setup_trainer_in_process(
        DEMO_SCENE, config.output_dir, STEPS, 0, "cpu", "reference", seed=SEED, **_overrides(config)
    )
    model = trainer.pipeline.model
    managers = [
        trainer.config.pipeline.datamanager.setup(device="cpu", test_mode="val", world_size=RANKS, local_rank=rank)
        for rank in range(RANKS)
    ]
    generators = [torch.Generator().manual_seed(SEED + rank) for rank in range(RANKS)]  # each rank's vote pixels
    offsets = model.gauss_params["vote_offsets"]
    model.train()
    seen = set()
    for step in range(STEPS):
        trainer.optimizers.zero_grad_all()
        for rank in range(RANKS):
            camera, batch = managers[rank].next_train(step)
            seen.add((rank, int(camera.metadata["cam_idx"])))
            model._vote_pixel_generator = generators[rank]
            outputs = model(camera)
            loss_dict = model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))
            sum(loss_dict.values()).backward()
        offsets.grad.div_(RANKS)
        trainer.optimizers.optimizer_scaler_step_all(trainer.grad_scaler)
        trainer.optimizers.scheduler_step_all(step)
        model.record_vote_support()  # the step's callback
    assert all(index % RANKS == rank for rank, index in seen) and len(seen) == RANKS * STEPS
    return offsets.detach().clone(), model.gauss_params["vote_support"].detach().clone()


def _overrides(config):
    model = config.pipeline.model
    return dict(
        datamanager_overrides={"cache_dir": config.pipeline.datamanager.cache_dir},
        retrofit_from=model.retrofit_from,
        num_downscales=model.num_downscales,
        resolution_schedule=model.resolution_schedule,
        vote_pixels_per_step=model.vote_pixels_per_step,
        foreground_min_masked_share=None,
    )


def test_two_ranks_over_gloo_match_one_process_seeing_the_same_views(retrofit_source, tmp_path):
    config = retrofit_config(tmp_path / "runs", retrofit_source, tmp_path / "cache")
    expected, support = one_process_two_views_a_step(config)
    assert expected.abs().max() > 0  # the steps moved the offsets

    result = str(tmp_path / "offsets.pt")
    torch.multiprocessing.spawn(_rank, args=(str(tmp_path / "rendezvous"), config, result), nprocs=RANKS)
    ranks = [torch.load(f"{result}.{rank}", weights_only=True) for rank in range(RANKS)]
    for name in ("vote_offsets", "vote_support"):
        assert torch.equal(ranks[0][name], ranks[1][name]), name  # the same step, the same support on every rank
    torch.testing.assert_close(ranks[0]["vote_offsets"], expected, rtol=1e-5, atol=1e-7)
    assert torch.equal(ranks[0]["vote_support"] > 0, support > 0) and (support > 0).any()
    # rank 0 wrote the run's checkpoint, with those offsets
    checkpoint = sorted(config.get_checkpoint_dir().glob("step-*.ckpt"))[-1]
    torch.testing.assert_close(load_gaussians(checkpoint, names=("vote_offsets",))["vote_offsets"], expected)


def test_ranks_share_the_training_views_and_several_train_only_a_retrofit(retrofit_source, tmp_path):
    assert training_ranks() == (0, 1) and training_ranks(4, 3) == (3, 4)
    config = trainer_config_in_process(DEMO_SCENE, tmp_path, 2, 0, "cpu", "run")
    with pytest.raises(VoteSplatInputError, match="train a retrofit only"):
        config.setup(local_rank=0, world_size=RANKS)


def _torchrun_rank(rank: int, port: int, config, result: str) -> None:
    """One rank as torchrun starts ns-train: its environment names the group, and nerfstudio's train_loop, which
    sees one process, seeds it as rank 0 before the trainer is made."""
    from nerfstudio.scripts.train import _set_random_seed

    os.environ.update(
        RANK=str(rank), LOCAL_RANK=str(rank), WORLD_SIZE=str(RANKS), MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port)
    )
    torch.set_num_threads(1)
    _set_random_seed(config.machine.seed)  # train_loop's seeding: global rank 0 on every torchrun rank
    try:
        trainer = config.setup(local_rank=0, world_size=1)
        assert trainer.ranks == RANKS and training_ranks() == (rank, RANKS)
        torch.save({"seed": torch.initial_seed(), "draw": torch.rand(4)}, f"{result}.{rank}")
    finally:
        dist.destroy_process_group()


def test_torchrun_ranks_join_the_group_seeded_as_nerfstudio_seeds_its_ranks(retrofit_source, tmp_path):
    """A rank started by torchrun is seeded with --machine.seed + its rank, as nerfstudio's own launch seeds it, so
    the ranks draw different vote pixels."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    config = retrofit_config(tmp_path / "runs", retrofit_source, tmp_path / "cache")
    result = str(tmp_path / "seeds.pt")
    torch.multiprocessing.spawn(_torchrun_rank, args=(port, config, result), nprocs=RANKS)
    ranks = [torch.load(f"{result}.{rank}", weights_only=True) for rank in range(RANKS)]
    assert [state["seed"] for state in ranks] == [SEED + rank for rank in range(RANKS)]
    assert not torch.equal(ranks[0]["draw"], ranks[1]["draw"])
