"""Compiles the fused vote kernels into Triton's on-disk cache, in a process of its own.

``vote_fused.start_warm_up`` runs this module as a child process while training sets up: Triton's compiler is
Python that holds the GIL for seconds, so compiling in a thread of the training process stalled its first
steps by as much (BENCHMARKS.md, session 12). The child compiles by running the training step's variant of each
kernel on a one-Gaussian scene; the training process's first vote step then loads them from the cache.

    python -m votesplat_ns.core.vote_warm_up LEVELS OPTIONS_JSON DEVICE
"""

from __future__ import annotations

import json
import sys
from typing import List

import torch
from torch import Tensor

from votesplat_ns.core.vote_fused import vote_losses_sampled
from votesplat_ns.core.vote_render import VoteRenderOptions


def warm_up(levels: int, options: VoteRenderOptions, device: torch.device) -> None:
    """Runs ``vote_losses_sampled`` forward and backward, with a support count, for ``levels`` [N, L, 3]
    float32 offsets and ``options`` on CUDA ``device`` (or on CPU under Triton's interpreter): the variant of
    each kernel a training step launches."""

    def f32(values) -> Tensor:
        return torch.tensor(values, dtype=torch.float32, device=device)

    offsets = torch.zeros(1, levels, 3, dtype=torch.float32, device=device, requires_grad=True)
    # the argument dtypes of a training step: gsplat's int32 tile lists, int64 pixel draws
    losses = vote_losses_sampled(
        f32([[8.0, 8.0]]),
        f32([[1.0, 0.0, 1.0]]),
        f32([0.5]),
        f32([[0.0, 0.0, 2.0]]),
        offsets,
        torch.eye(4, dtype=torch.float32, device=device),
        f32([[8.0, 0.0, 8.0], [0.0, 8.0, 8.0], [0.0, 0.0, 1.0]]),
        torch.zeros(2, dtype=torch.int64, device=device),
        torch.zeros(1, dtype=torch.int64, device=device),
        torch.ones(levels, 1, dtype=torch.int32, device=device),
        torch.full((levels, 2, 2), 0.5, dtype=torch.float32, device=device),
        1,
        1.0,
        torch.zeros(1, 1, dtype=torch.int32, device=device),
        torch.zeros(1, dtype=torch.int32, device=device),
        16,
        options,
        (1.0, 0.5),
        (
            torch.zeros(1, levels, dtype=torch.float32, device=device),
            torch.full((1, levels), -1, dtype=torch.int32, device=device),
            0,
        ),
    )
    losses["total"].backward()
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def main(argv: List[str]) -> int:
    levels, options, device = argv
    warm_up(int(levels), VoteRenderOptions(**json.loads(options)), torch.device(device))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
