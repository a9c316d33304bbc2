"""Counts the torch ops of one training vote step on the fused path, as ns-train runs it, on CPU.

The step: ``VoteSplatModel._vote_losses`` (what ``get_metrics_dict`` computes), the trainer's sum of the loss
dict (``functools.reduce(torch.add, ...)``, one colour loss standing in for splatfacto's), the backward and
``record_vote_support``; the model as ``count_vote_ops.model_step`` builds it, the Triton kernels under
``TRITON_INTERPRET=1``. Prints the launching aten ops (all aten ops, views included), the host syncs and the
Triton launches. Counts the tree it runs in, so an older tree (``git archive``) counts with the same script:

    python benchmarks/count_training_vote_step.py
    (cd /tmp/old && python /path/to/benchmarks/count_training_vote_step.py)
"""

from __future__ import annotations

import functools
import os
import sys

os.environ["TRITON_INTERPRET"] = "1"  # before triton is imported
os.environ["VOTESPLAT_VOTE_BACKEND"] = "triton"
sys.path.insert(0, os.getcwd())  # the tree it runs in

import torch  # noqa: E402

from benchmarks import count_vote_ops  # noqa: E402


def main() -> int:
    model, step = count_vote_ops.model_step(levels=2, n=600, width=64, height=48, pixels=256)
    batch = getattr(step, "batch", None)
    if batch is None:  # a tree from before step.batch: the step's closure holds it
        batch = next(cell.cell_contents for cell in step.__closure__ or () if isinstance(cell.cell_contents, dict))
    colour = torch.zeros((), requires_grad=True)

    def vote_step() -> None:
        model.gauss_params["vote_offsets"].grad = None
        returned = model._vote_losses(batch)
        losses = returned[0] if isinstance(returned, tuple) else returned  # (losses, metrics) since 497537f
        functools.reduce(torch.add, [colour * 1.0, *losses.values()]).backward()
        model.record_vote_support()

    vote_step()  # warm-up: first-call imports and caches out of the count
    with count_vote_ops.OpCounter() as counter:
        vote_step()
    print(
        f"{os.getcwd()}: launching ops (all aten ops) / host syncs: {counter.total_kernels} ({counter.total_ops}) / "
        f"{counter.total_syncs}; Triton launches {counter.triton_launches}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
