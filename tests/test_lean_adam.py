"""LeanFusedAdam (every Gaussian group's optimizer) against torch.optim.Adam(fused=True), and the Gaussians'
groups' fused step against splatfacto's multi-tensor Adam."""

from __future__ import annotations

import pytest
import torch
import torch.optim.adam as torch_adam

from votesplat_ns.ns.lean_adam import LeanFusedAdam, NeverStepsOptimizer

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def _pair(device, **kwargs):
    start = torch.randn(300, 2, 3, generator=torch.Generator().manual_seed(0)).to(device)
    reference, lean = torch.nn.Parameter(start.clone()), torch.nn.Parameter(start.clone())
    options = dict(lr=1e-3, eps=1e-15, fused=True, **kwargs)
    return (reference, torch.optim.Adam([reference], **options)), (lean, LeanFusedAdam([lean], **options))


def _prune(param, optimizer, keep):
    """What densification does to an optimizer: a new parameter of the kept rows, its state cut the same way."""
    state = optimizer.state.pop(param)
    new = torch.nn.Parameter(param.detach()[keep].clone())
    optimizer.param_groups[0]["params"] = [new]
    optimizer.state[new] = {k: (v if k == "step" else v[keep].clone()) for k, v in state.items()}
    return new


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("weight_decay", [0.0, 0.01])
def test_lean_steps_equal_torch_fused_adam(device, weight_decay, monkeypatch):
    """The same bits as torch's fused Adam over a run with a scheduled lr, a step without a gradient and a
    pruning of the parameter, and every step after the first (which makes the state) skips Adam.step's body."""
    (ref, ref_opt), (lean, lean_opt) = _pair(device, weight_decay=weight_decay)
    calls = []
    original = torch_adam.adam
    monkeypatch.setattr(torch_adam, "adam", lambda *a, **k: calls.append(1) or original(*a, **k))
    gen = torch.Generator().manual_seed(1)
    for step in range(40):
        if step == 15:
            for opt in (ref_opt, lean_opt):
                opt.param_groups[0]["lr"] = 3e-4  # a scheduler's change
        if step == 25:
            keep = torch.arange(ref.shape[0], device=device) % 3 != 0
            ref, lean = _prune(ref, ref_opt, keep), _prune(lean, lean_opt, keep)
        grad = torch.randn(ref.shape, generator=gen).to(device)
        ref.grad = grad.clone()
        lean.grad = None if step == 10 else grad.clone()  # no vote this step: nerfstudio does not step it,
        if step == 10:  # but a caller that does gets Adam's (which skips a parameter without a gradient)
            ref.grad = None
        ref_opt.step()
        lean_opt.step()
        assert torch.equal(lean, ref), step
    assert torch.equal(lean_opt.state[lean]["exp_avg_sq"], ref_opt.state[ref]["exp_avg_sq"])
    assert torch.equal(lean_opt.state[lean]["step"], ref_opt.state[ref]["step"])
    # Adam's body ran for each of the reference's 39 steps with a gradient (and its step without one), and
    # for the lean optimizer only where a step was not plain: the first (no state yet) and the one without
    # a gradient
    assert len(calls) == 40 + 2


def test_not_plain_steps_go_through_adam_with_hooks_once(monkeypatch):
    """A closure or a grad scaler's attributes take Adam.step; step hooks run once a step either way."""
    (_, _), (lean, opt) = _pair("cpu")
    lean.grad = torch.ones_like(lean)
    opt.step()  # makes the state
    hooks = []
    opt.register_step_pre_hook(lambda *args: hooks.append("pre"))
    opt.register_step_post_hook(lambda *args: hooks.append("post"))
    calls = []
    original = torch_adam.adam
    monkeypatch.setattr(torch_adam, "adam", lambda *a, **k: calls.append(k.get("grad_scale")) or original(*a, **k))
    torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))])  # Optimizer wraps Adam.step with the hooks now
    opt.step()
    assert calls == [] and hooks == ["pre", "post"]
    assert opt.step(closure=lambda: torch.tensor(1.0)) == torch.tensor(1.0)
    assert len(calls) == 1 and hooks == ["pre", "post"] * 2
    opt.grad_scale, opt.found_inf = torch.ones(()), torch.zeros(())  # as GradScaler.step sets them
    opt.step()
    assert len(calls) == 2 and calls[-1] is not None and hooks == ["pre", "post"] * 3


def test_the_gaussian_groups_use_them():
    from votesplat_ns.ns.method import splatfacto_optimizers
    from votesplat_ns.ns.run import SPLAT_PARAM_NAMES

    optimizers = splatfacto_optimizers()
    for name in (*SPLAT_PARAM_NAMES, "vote_offsets"):
        optimizer = optimizers[name]["optimizer"].setup([torch.nn.Parameter(torch.zeros(4, 2, 3))])
        assert type(optimizer) is LeanFusedAdam and optimizer.param_groups[0]["fused"], name
    support = optimizers["vote_support"]["optimizer"].setup([torch.nn.Parameter(torch.zeros(4, 2))])
    assert type(support) is NeverStepsOptimizer


def _steps(make, steps: int = 200):
    """A parameter after ``steps`` Adam steps of ``make`` at splatfacto's means settings, on fixed gradients."""
    param = torch.nn.Parameter(torch.randn(500, 3, generator=torch.Generator().manual_seed(2)))
    optimizer = make(param)
    gen = torch.Generator().manual_seed(3)
    for _ in range(steps):
        param.grad = (torch.randn(param.shape, generator=gen) + 2.0) * 1e-3  # mostly one sign: params travel
        optimizer.step()
    return param.detach()


def test_the_fused_gaussian_step_is_splatfacto_adam_up_to_rounding_and_unfused_is_it_bitwise():
    """The Gaussians' groups take torch's fused Adam, splatfacto's multi-tensor Adam's update in other rounding;
    ``--optimizers.<group>.optimizer.fused False`` gives splatfacto's Adam back, bit for bit."""
    from votesplat_ns.ns.method import splatfacto_optimizers

    config = splatfacto_optimizers()["means"]["optimizer"]
    splatfacto = _steps(lambda p: torch.optim.Adam([p], lr=config.lr, eps=config.eps, foreach=True))
    fused = _steps(lambda p: config.setup([p]))
    moved = (splatfacto - _steps(lambda p: torch.optim.SGD([p], lr=0.0))).abs()
    assert moved.min() > 0.01  # every coordinate travelled 60-200 lr
    torch.testing.assert_close(fused, splatfacto, rtol=0, atol=1e-6)
    config.fused = False
    unfused = config.setup([torch.nn.Parameter(torch.zeros(1))])
    assert not unfused.param_groups[0]["fused"]
    default = _steps(lambda p: torch.optim.Adam([p], lr=config.lr, eps=config.eps))  # splatfacto's, on this device
    assert torch.equal(_steps(lambda p: config.setup([p])), default)


@pytest.mark.parametrize(
    "make", [lambda p: LeanFusedAdam([p], lr=1e-3, fused=True), lambda p: NeverStepsOptimizer([p])]
)
def test_zero_grad_clears_as_torch_does(make):
    """set_to_none (nerfstudio's call) leaves no gradient; set_to_none=False zeroes it in place, as torch does."""
    param = torch.nn.Parameter(torch.ones(3, 2))
    optimizer = make(param)
    param.grad = torch.full_like(param, 2.0)
    optimizer.zero_grad()
    assert param.grad is None
    param.grad = torch.full_like(param, 2.0)
    grad = param.grad
    optimizer.zero_grad(set_to_none=False)
    assert param.grad is grad and torch.equal(grad, torch.zeros_like(grad))


def test_never_steps_keeps_its_parameter_through_steps_densification_and_resume():
    """A gradient does not move it; gsplat's densification edits it as an Adam's entry (rows kept and copied,
    no state); a checkpoint written with the earlier lr-0 Adam for this group loads into it."""
    from gsplat.strategy.ops import duplicate, remove

    param = torch.nn.Parameter(torch.arange(12.0).reshape(6, 2))
    optimizer = NeverStepsOptimizer([param])
    param.grad = torch.ones_like(param)
    assert optimizer.step() is None and torch.equal(param, torch.arange(12.0).reshape(6, 2))
    assert optimizer.step(closure=lambda: torch.tensor(3.0)) == 3.0
    params = torch.nn.ParameterDict({"vote_support": param})
    optimizers = {"vote_support": optimizer}
    duplicate(params, optimizers, {}, torch.tensor([True, False, False, False, False, True]))
    remove(params, optimizers, {}, torch.tensor([False, True] + [False] * 6))
    kept = params["vote_support"]
    assert torch.equal(kept.detach(), torch.tensor([[0.0, 1], [4, 5], [6, 7], [8, 9], [10, 11], [0, 1], [10, 11]]))
    assert optimizer.param_groups[0]["params"][0] is kept and not any(optimizer.state.values())
    old = torch.optim.Adam([torch.nn.Parameter(torch.zeros(7, 2))], lr=0.0, fused=True)  # never stepped
    optimizer.load_state_dict(old.state_dict())
    kept.grad = torch.ones_like(kept)
    optimizer.step()
    assert optimizer.param_groups[0]["params"][0] is kept and torch.equal(kept.detach()[0], torch.tensor([0.0, 1]))
