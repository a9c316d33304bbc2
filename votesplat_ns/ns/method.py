"""The ``votesplat`` method, registered through the ``nerfstudio.method_configs`` entry point.

Importing this module (nerfstudio does so at start-up of every ``ns-*`` command) applies the
plugin's process-wide patches of upstream code, all listed in :mod:`votesplat_ns.ns.patches`.
"""

from __future__ import annotations

import gc
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, Literal, Optional, Type

from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig, OptimizerConfig
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification

from votesplat_ns.ns import patches
from votesplat_ns.ns.datamanager import VoteDataManagerConfig
from votesplat_ns.ns.lean_adam import LeanFusedAdam, NeverStepsOptimizer
from votesplat_ns.ns.model import VoteSplatModelConfig
from votesplat_ns.ns.trainer import VoteSplatTrainer


@dataclass
class FusedAdamOptimizerConfig(AdamOptimizerConfig):
    """Adam as one fused kernel per step (torch's ``fused=True``, CPU and CUDA).

    For every Gaussian group: each steps on every training step, where torch's default multi-tensor Adam
    costs ~10 launches of host time, and torch's fused one mostly Python around its two ops (LeanFusedAdam
    runs those two itself). The same update as splatfacto's Adam up to float rounding; ``fused`` False
    (``--optimizers.<group>.optimizer.fused False``) gives torch's multi-tensor Adam, splatfacto's, back."""

    _target: Type = LeanFusedAdam
    fused: bool = True
    """One fused Adam kernel per step; False: torch's multi-tensor Adam (splatfacto's), the same update up to rounding."""


@dataclass
class NeverStepsOptimizerConfig(OptimizerConfig):
    """For a ``gauss_params`` entry that is kept, not trained (``vote_support``): gsplat's densification needs an
    optimizer per entry; this one never changes it and costs a step no Adam."""

    _target: Type = NeverStepsOptimizer
    lr: float = 0.0
    """Unused (never steps)."""


def splatfacto_optimizers(max_steps: int = 30000) -> dict:
    """splatfacto's optimizer settings (nerfstudio 1.1.5 method_configs), plus the vote groups. The Gaussians'
    groups take their Adam step as one fused kernel (``FusedAdamOptimizerConfig``): the host time of their six
    multi-tensor steps was a larger part of a training step than a vote step (BENCHMARKS.md, "Training time")."""
    return {
        "means": {
            "optimizer": FusedAdamOptimizerConfig(lr=1.6e-4, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=max_steps),
        },
        "features_dc": {"optimizer": FusedAdamOptimizerConfig(lr=0.0025, eps=1e-15), "scheduler": None},
        "features_rest": {"optimizer": FusedAdamOptimizerConfig(lr=0.0025 / 20, eps=1e-15), "scheduler": None},
        "opacities": {"optimizer": FusedAdamOptimizerConfig(lr=0.05, eps=1e-15), "scheduler": None},
        "scales": {"optimizer": FusedAdamOptimizerConfig(lr=0.005, eps=1e-15), "scheduler": None},
        "quats": {"optimizer": FusedAdamOptimizerConfig(lr=0.001, eps=1e-15), "scheduler": None},
        "camera_opt": {
            "optimizer": AdamOptimizerConfig(lr=1e-4, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(
                lr_final=5e-7, max_steps=max_steps, warmup_steps=1000, lr_pre_warmup=0
            ),
        },
        "bilateral_grid": {
            "optimizer": AdamOptimizerConfig(lr=2e-3, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(
                lr_final=1e-4, max_steps=max_steps, warmup_steps=1000, lr_pre_warmup=0
            ),
        },
        # Offsets are in scene units; Adam makes the step size independent of the loss weight.
        "vote_offsets": {
            "optimizer": FusedAdamOptimizerConfig(lr=1e-3, eps=1e-15),
            "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=max_steps),
        },
        # Bookkeeping only: counted by the vote steps, never trained.
        "vote_support": {"optimizer": NeverStepsOptimizerConfig(), "scheduler": None},
    }


def votesplat_trainer_config() -> TrainerConfig:
    return TrainerConfig(
        _target=VoteSplatTrainer,  # resumes read checkpoints safely (ns/trainer.py)
        method_name="votesplat",
        steps_per_eval_image=100,
        steps_per_eval_batch=0,
        steps_per_save=2000,
        steps_per_eval_all_images=1000,
        max_num_iterations=30000,
        mixed_precision=False,
        pipeline=VanillaPipelineConfig(
            datamanager=VoteDataManagerConfig(
                dataparser=NerfstudioDataParserConfig(load_3D_points=True),
                cache_images_type="uint8",
            ),
            model=VoteSplatModelConfig(),
        ),
        optimizers=splatfacto_optimizers(),
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    )


# Shown at the top of `ns-train votesplat --help`, above ~90 options of splatfacto's: point to the method's own.
VOTESPLAT_DESCRIPTION = (
    "VoteSplat: splatfacto plus a 3D vote offset per Gaussian, for instances, click and text selection. "
    "Its own options: --pipeline.model.vote-start-step, --pipeline.model.vote-every-n-steps and the other "
    "--pipeline.model.vote-* options (vote loss), --pipeline.model.retrofit-from (add instances to a trained "
    "splatfacto run); --pipeline.datamanager.mask-source, --pipeline.datamanager.mask-folder, "
    "--pipeline.datamanager.sam-checkpoint and --pipeline.datamanager.cache-dir (where masks come from and are cached). "
    "README sections: 'Using it on your own capture', 'Masks', 'Troubleshooting'."
)

votesplat_method = MethodSpecification(config=votesplat_trainer_config(), description=VOTESPLAT_DESCRIPTION)

# after the method spec exists: installing the export hook may import nerfstudio's exporter,
# which imports the method configs (this module)
patches.apply()


def setup_trainer_in_process(*args: Any, **kwargs: Any):
    """A set-up (not yet trained) nerfstudio Trainer of :func:`trainer_config_in_process`'s config (its arguments)."""
    return setup_trainer(trainer_config_in_process(*args, **kwargs))


def trainer_config_in_process(
    data: Path,
    output_dir: Path,
    steps: int,
    vote_start: int,
    device: Literal["cpu", "cuda", "mps"] = "cpu",
    timestamp: str = "run",
    mask_folder: Optional[Path] = None,
    seed: int = 42,
    datamanager_overrides: Optional[Dict[str, Any]] = None,
    load_dir: Optional[Path] = None,
    **model_overrides,
) -> TrainerConfig:
    """votesplat's TrainerConfig of ``steps`` steps, votes from ``vote_start`` on.

    No evaluation or intermediate checkpoints; the vote cache goes to ``output_dir/vote_cache``;
    ``mask_folder`` switches to the folder mask source. ``model_overrides`` set model config fields,
    ``datamanager_overrides`` datamanager config fields (e.g. ``border_masks``). ``seed``: ``--machine.seed``.
    ``load_dir``: a run's nerfstudio_models/ folder to resume from, as ``ns-train --load-dir`` (the ``steps``
    more steps continue from its latest checkpoint).
    """
    config = votesplat_trainer_config()
    config.machine.device_type = device
    config.machine.seed = seed
    config.vis = "tensorboard"
    config.output_dir = output_dir
    config.timestamp = timestamp
    config.max_num_iterations = steps
    config.steps_per_eval_image = 10 * steps
    config.steps_per_eval_all_images = 10 * steps
    config.steps_per_save = 10 * steps
    config.load_dir = load_dir
    config.data = data
    datamanager, model = config.pipeline.datamanager, config.pipeline.model
    assert isinstance(datamanager, VoteDataManagerConfig) and isinstance(model, VoteSplatModelConfig)
    datamanager.data = data
    datamanager.cache_dir = output_dir / "vote_cache"
    if mask_folder is not None:
        datamanager.mask_source = "folder"
        datamanager.mask_folder = mask_folder
    model.vote_start_step = vote_start
    for target, overrides in ((model, model_overrides), (datamanager, datamanager_overrides or {})):
        for name, value in overrides.items():
            if not hasattr(target, name):
                raise ValueError(f"votesplat's {type(target).__name__} has no field {name!r}")
            setattr(target, name, value)
    config.set_timestamp()
    return config


def setup_trainer(config: TrainerConfig):
    """A set-up nerfstudio Trainer of ``config`` in this process, as ns-train's train_loop makes it: the config
    saved, Python, NumPy and torch seeded with ``config.machine.seed``."""
    from nerfstudio.scripts.train import _set_random_seed
    from nerfstudio.utils import writer

    config.save_config()
    # nerfstudio keeps its event writers in module globals: a second run in this process must not log into the first's
    for event_writer in list(writer.EVENT_WRITERS):
        if hasattr(event_writer, "tb_writer"):
            event_writer.tb_writer.close()
    writer.EVENT_WRITERS.clear()
    writer.EVENT_STORAGE.clear()
    writer.GLOBAL_BUFFER.clear()
    _set_random_seed(config.machine.seed)  # ns-train's train_loop's own seeding (rank 0)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def train_in_process(*args: Any, **kwargs: Any) -> Path:
    """Train votesplat in this process (tests, benchmarks/quality.py); returns the run's config.yml.

    The arguments are :func:`trainer_config_in_process`'s.
    """
    import torch

    trainer = setup_trainer_in_process(*args, **kwargs)
    device = trainer.config.machine.device_type
    config_path = trainer.config.get_base_dir() / "config.yml"
    trainer.train()
    del trainer
    gc.collect()
    if device == "cuda":
        torch.cuda.empty_cache()
    return config_path
