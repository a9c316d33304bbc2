"""Compiles the fused vote kernels into Triton's on-disk cache, in a process of its own.

``vote_fused.start_warm_up`` runs this module as child processes while training sets up: Triton's compiler is
Python that holds the GIL for seconds, so compiling in a thread of the training process stalled its first
steps by as much (BENCHMARKS.md, "Fused vote kernels"). A child compiles by running the training step's variant of each
kernel on a one-Gaussian scene; the training process's first vote step then loads them from the cache. On CUDA
two children share the work: one runs the forward (its walk and reduction kernels), the other only the backward
kernel, on a forward that found no member anywhere, so the first vote step waits for the longer of the two
compiles instead of their sum (BENCHMARKS.md, "Fused vote kernels"). Both launch the kernels for real: the variant a
launch compiles is the one a training step looks up (Triton's compile-only ``warmup`` stored another on the
H100).

    python -m votesplat_ns.core.vote_warm_up LEVELS OPTIONS_JSON DEVICE [PART]    PART: all, forward, backward
"""

from __future__ import annotations

import json
import sys
from typing import List

import torch
from torch import Tensor

from votesplat_ns.core import vote_fused, vote_kernel
from votesplat_ns.core.vote_render import VoteRenderOptions

PARTS = ("all", "forward", "backward")


def warm_up(levels: int, options: VoteRenderOptions, device: torch.device, part: str = "all") -> None:
    """Runs ``vote_losses_sampled`` forward and backward, with a support count, for ``levels`` [N, L, 3]
    float32 offsets and ``options`` on CUDA ``device`` (or on CPU under Triton's interpreter): the variant of
    each kernel a training step launches. ``part`` "forward" stops after the forward; "backward" launches only
    the backward kernel: the forward kernels do not run and every pixel's |M| is set to 0 instead, so the
    backward reads nothing else of the forward's (unwritten) outputs."""
    if part not in PARTS:
        raise ValueError(f"part must be one of {', '.join(PARTS)}, got {part!r}")
    if part == "backward":
        launch = vote_kernel._launch

        def backward_only(kernel, grid, *args, **kwargs) -> None:
            if kernel is vote_fused._fused_fwd_kernel:
                args[kernel.arg_names.index("walk_ptr")].zero_()  # row 0 of the walk buffer: |M| per pixel
            elif kernel is vote_fused._fused_bwd_kernel:
                launch(kernel, grid, *args, **kwargs)

        vote_kernel._launch = backward_only

    def f32(values) -> Tensor:
        return torch.tensor(values, dtype=torch.float32, device=device)

    offsets = torch.zeros(1, levels, 3, dtype=torch.float32, device=device, requires_grad=True)
    # the argument dtypes of a training step: gsplat's int32 tile lists, int64 pixel draws, the datamanager's
    # int32 voting pixels and int16 labels (vote_maps.voting_pixels, label_tensor)
    losses = vote_fused.vote_losses_sampled(
        f32([[8.0, 8.0]]),
        f32([[1.0, 0.0, 1.0]]),
        f32([0.5]),
        f32([[0.0, 0.0, 2.0]]),
        offsets,
        torch.eye(4, dtype=torch.float32, device=device),
        f32([[8.0, 0.0, 8.0], [0.0, 8.0, 8.0], [0.0, 0.0, 1.0]]),
        torch.zeros(2, dtype=torch.int64, device=device),
        torch.zeros(1, dtype=torch.int32, device=device),
        torch.ones(levels, 1, dtype=torch.int16, device=device),
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
    if part != "forward":
        losses["total"].backward()
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def main(argv: List[str]) -> int:
    levels, options, device, *part = argv
    warm_up(int(levels), VoteRenderOptions(**json.loads(options)), torch.device(device), *part)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
