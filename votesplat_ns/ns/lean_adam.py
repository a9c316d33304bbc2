"""The vote groups' optimizers: torch's fused Adam without most of its Python on a plain step, and one that
never steps.

A vote step's offsets take one Adam step; torch.optim.Adam(fused=True) spends most of that step's host time
in Python around its two ops (grouping tensors by device, the functional wrapper's checks, the grad-mode
decorator). ``LeanFusedAdam.step`` runs those two ops itself when nothing else is asked of it: inside
training on the H100's host the offsets' step fell from 0.16 to 0.11-0.13 ms (BENCHMARKS.md, "Training time").

Both also clear gradients without Optimizer.zero_grad's profiler scope (two dispatcher calls around a loop):
nerfstudio clears every group on every step, and on the H100's host the two vote groups' clears added
0.03-0.16 ms to every step, voting or not (BENCHMARKS.md, "Training time").
"""

from __future__ import annotations

import torch


class _ClearsWithoutProfilerScope:
    """``zero_grad(set_to_none=True)``, nerfstudio's call, as a plain loop that sets every gradient to None; the
    other form is the optimizer's own."""

    def zero_grad(self, set_to_none: bool = True) -> None:
        if not set_to_none:
            super().zero_grad(set_to_none)  # type: ignore[misc]
            return
        for group in self.param_groups:  # type: ignore[attr-defined]
            for param in group["params"]:
                param.grad = None


class LeanFusedAdam(_ClearsWithoutProfilerScope, torch.optim.Adam):
    """torch.optim.Adam(fused=True) whose plain steps run torch's fused path directly: ``_foreach_add_`` on
    the step count, then ``_fused_adam_`` (the same ops with the same arguments, so the same bits).

    A plain step: one group with one parameter that has a dense gradient and a state (made by an earlier
    step), a float lr, no closure, no grad scaler (GradScaler sets ``grad_scale``/``found_inf``), no AMSGrad,
    maximize, capturable, differentiable or decoupled decay. Any other step is Adam.step's. Step hooks and
    the profiler label still run: Optimizer wraps this method as it wraps Adam.step.
    """

    def step(self, closure=None):  # type: ignore[override]
        if closure is not None or not self._plain_step():
            adam_step = torch.optim.Adam.step
            # Adam's step as Optimizer wrapped it (once an Adam was made) would run the step hooks a second time
            if getattr(adam_step, "hooked", False):
                adam_step = adam_step.__wrapped__
            return adam_step(self, closure)
        group = self.param_groups[0]
        param = group["params"][0]
        state = self.state[param]
        beta1, beta2 = group["betas"]
        steps = [state["step"]]
        # torch's private ops, on purpose: the ops torch.optim.Adam(fused=True) runs (class docstring)
        with torch.no_grad():
            torch._foreach_add_(steps, 1)  # pyright: ignore[reportPrivateImportUsage]
            torch._fused_adam_(  # pyright: ignore[reportPrivateImportUsage]
                [param],
                [param.grad],
                [state["exp_avg"]],
                [state["exp_avg_sq"]],
                [],
                steps,
                amsgrad=False,
                lr=group["lr"],
                beta1=beta1,
                beta2=beta2,
                weight_decay=group["weight_decay"],
                eps=group["eps"],
                maximize=False,
                grad_scale=None,
                found_inf=None,
            )
        return None

    def _plain_step(self) -> bool:
        if len(self.param_groups) != 1 or not hasattr(torch, "_fused_adam_"):
            return False
        group = self.param_groups[0]
        if len(group["params"]) != 1 or not group.get("fused"):
            return False
        if any(group.get(flag) for flag in ("amsgrad", "maximize", "capturable", "differentiable")):
            return False
        if group.get("decoupled_weight_decay") or isinstance(group["lr"], torch.Tensor):
            return False
        if getattr(self, "grad_scale", None) is not None or getattr(self, "found_inf", None) is not None:
            return False
        param = group["params"][0]
        grad = param.grad
        state = self.state.get(param)
        return grad is not None and not grad.is_sparse and bool(state) and "step" in state


class NeverStepsOptimizer(_ClearsWithoutProfilerScope, torch.optim.Optimizer):
    """The optimizer of a ``gauss_params`` entry that is kept, not trained (``vote_support``, a count).

    gsplat's densification edits one optimizer per entry (it moves each entry's optimizer state along with
    the rows it keeps or copies), so the entry needs one; this one holds no state, and its ``step`` leaves
    the parameter as it is, with or without a gradient. ``lr`` and ``eps`` are taken (nerfstudio's optimizer
    config passes them) and kept in the group, unused."""

    def __init__(self, params, lr: float = 0.0, eps: float = 1e-8):
        super().__init__(params, {"lr": lr, "eps": eps})

    def step(self, closure=None):  # type: ignore[override]
        if closure is not None:
            with torch.enable_grad():
                return closure()
        return None
