"""A retrofit (``--pipeline.model.retrofit-from``) trained by several processes, one per GPU, through torch.distributed.

Each rank votes on its own training views (the datamanager gives rank r of N the views r, r + N, ...: see
:func:`training_ranks`), computes the offsets' gradient on its view, and before every optimizer step the
gradients are averaged over the ranks (one all-reduce of the offsets' gradient, 12 bytes per Gaussian and
level); every rank then takes the same Adam step, so the offsets stay the same on every rank and rank 0's
checkpoint is the run's. Only the offsets train (the scene is frozen in a retrofit); the vote support each rank
counts is made its maximum over the ranks at the same time (4 bytes per Gaussian and level), so a Gaussian
supervised in any rank's views is foreground in that checkpoint. A step of N ranks is the step one process would
take on the mean of the N views' gradients.

Launch, on one host with N GPUs (NCCL):

    ns-train votesplat --machine.num-devices N --pipeline.model.retrofit-from <run or ply> --data <capture>
    torchrun --standalone --nproc-per-node N $(which ns-train) votesplat --pipeline.model.retrofit-from ... --data ...

and on the CPU (gloo), with torchrun and ``--machine.device-type cpu``. ``--machine.num-devices`` is
nerfstudio's own launch (one process per GPU, a process group over NCCL); under torchrun the trainer joins
the group torchrun describes (:func:`join_launched_group`) and seeds rank r with ``--machine.seed`` + r, as
nerfstudio's launch does.

nerfstudio's own data-parallel path cannot train the votes: its pipeline wraps the model in
``DistributedDataParallel``, whose forward must produce every output a loss is taken from, while the vote
loss is computed after the forward (``get_metrics_dict`` / ``get_loss_dict``; a vote-only step's forward
returns nothing), so DDP's reducer fails at the first backward ("Expected to mark a variable ready only
once"); its ranks would also all draw the same views. :class:`~votesplat_ns.ns.trainer.VoteSplatTrainer`
therefore builds the pipeline as for one process and averages the gradients in its optimizers
(:class:`DataParallelOptimizers`).
"""

from __future__ import annotations

import os
from datetime import timedelta
from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch
import torch.distributed as dist
from nerfstudio.engine.optimizers import Optimizers

from votesplat_ns.errors import VoteSplatInputError

# the groups a retrofit trains, whose gradients the ranks average
TRAINED_GROUPS = ("vote_offsets",)
# the groups whose values are counts each rank keeps of its own views (the fused vote backward counts the support
# of the pixels it drew), made the element-wise maximum over the ranks at each step: every consumer of the
# support asks whether it is > 0, which the maximum answers as the views of all ranks would
COUNTED_GROUPS = ("vote_support",)
# ranks wait this long for each other at a collective (the vote cache build of a large capture included)
RANKS_TIMEOUT = timedelta(hours=6)


def distributed_ranks() -> Optional[Tuple[int, int]]:
    """(rank, world size) of this process in an initialised process group of several ranks, else None."""
    if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
        return dist.get_rank(), dist.get_world_size()
    return None


def training_ranks(world_size: int = 1, local_rank: int = 0) -> Tuple[int, int]:
    """(rank, ranks) that share the training views: the given ``world_size`` / ``local_rank`` when several, else
    the process group's (the trainer builds the pipeline as for one process), else (0, 1)."""
    if world_size > 1:
        return local_rank, world_size
    return distributed_ranks() or (0, 1)


def check_data_parallel(config: Any, world_size: int) -> None:
    """One line when ``world_size`` ranks cannot train this run: only a retrofit trains on several."""
    if world_size > 1 and getattr(config.pipeline.model, "retrofit_from", None) is None:
        raise VoteSplatInputError(
            f"{world_size} processes (--machine.num-devices or torchrun) train a retrofit only, whose offsets are "
            "the one thing that trains: add --pipeline.model.retrofit-from <trained run or .ply>, or train on one "
            "GPU (--machine.num-devices 1)"
        )


def launched_ranks() -> Optional[Tuple[int, int, int]]:
    """(rank, world size, local rank) when torchrun (or another launcher) started this process as one of several."""
    world = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if world <= 1 or "RANK" not in os.environ:
        return None
    rank = int(os.environ["RANK"])
    return rank, world, int(os.environ.get("LOCAL_RANK", rank))


def join_launched_group(device_type: str) -> Optional[Tuple[int, int, int]]:
    """Under torchrun: join its process group (NCCL on CUDA, gloo otherwise) unless joined already, and return
    (rank, world size, local rank); None when this process was started alone."""
    launched = launched_ranks()
    if launched is None:
        return None
    rank, world, local_rank = launched
    if device_type == "cuda":
        available = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if local_rank >= available:
            raise VoteSplatInputError(
                f"torchrun started local rank {local_rank}, but this machine has {available} GPU(s): start at most "
                f"{available} processes per node (--nproc-per-node)"
            )
        torch.cuda.set_device(local_rank)
    if not dist.is_initialized():
        dist.init_process_group("nccl" if device_type == "cuda" else "gloo", timeout=RANKS_TIMEOUT)
    return rank, world, local_rank


def rank_zero_value(value: Any) -> Any:
    """Rank 0's ``value`` (picklable) on every rank of the process group."""
    box: List[Any] = [value]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def average_gradients(params: Sequence[torch.Tensor], world_size: int) -> None:
    """Replace each parameter's gradient by its mean over the ranks (a missing one counts as zeros)."""
    for param in params:
        if param.grad is None:
            param.grad = torch.zeros_like(param)
        dist.all_reduce(param.grad, op=dist.ReduceOp.SUM)
        param.grad.div_(world_size)


def maximum_over_ranks(params: Sequence[torch.Tensor]) -> None:
    """Replace each parameter's values by their element-wise maximum over the ranks."""
    with torch.no_grad():
        for param in params:
            dist.all_reduce(param.data, op=dist.ReduceOp.MAX)


def broadcast_parameters(params: Sequence[torch.Tensor]) -> None:
    """Give every rank rank 0's values of ``params`` (the ranks start from the same offsets)."""
    with torch.no_grad():
        for param in params:
            dist.broadcast(param.data, src=0)


class DataParallelOptimizers(Optimizers):
    """nerfstudio's optimizers whose steps first average the gradients of the ``averaged`` groups over the ranks
    and make the values of the ``counted`` groups their maximum over the ranks."""

    def __init__(
        self,
        config: Dict[str, Any],
        param_groups: Dict[str, List],
        averaged: Sequence[str],
        world_size: int,
        counted: Sequence[str] = (),
    ):
        super().__init__(config, param_groups)
        self.averaged = tuple(name for name in averaged if name in self.optimizers)
        self.counted = tuple(name for name in counted if name in self.optimizers)
        self.world_size = int(world_size)

    def _held(self, names: Sequence[str]) -> List[torch.Tensor]:
        # as the optimizers hold them now (a resume may have replaced them: VoteSplatModel.adopt_optimizers)
        return [param for name in names for group in self.optimizers[name].param_groups for param in group["params"]]

    def averaged_parameters(self) -> List[torch.Tensor]:
        """The parameters whose gradients the ranks average."""
        return self._held(self.averaged)

    def counted_parameters(self) -> List[torch.Tensor]:
        """The parameters whose values the ranks make their maximum."""
        return self._held(self.counted)

    def average_gradients(self) -> None:
        average_gradients(self.averaged_parameters(), self.world_size)
        maximum_over_ranks(self.counted_parameters())

    def optimizer_step_all(self) -> None:
        self.average_gradients()
        super().optimizer_step_all()

    def optimizer_scaler_step_all(self, grad_scaler) -> None:
        self.average_gradients()
        super().optimizer_scaler_step_all(grad_scaler)

    def optimizer_scaler_step_some(self, grad_scaler, param_groups: List[str]) -> None:
        if any(name in param_groups for name in self.averaged):
            self.average_gradients()
        super().optimizer_scaler_step_some(grad_scaler, param_groups)
