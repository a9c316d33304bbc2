"""Launches of compiled Triton kernels without the JIT's dispatch (votesplat_ns.core.triton_launch).

On CPU: which launches go through ``kernel[grid]`` and which call the remembered launcher, and with what
arguments, on a stand-in kernel. On CUDA: the fused vote losses launched directly equal the JIT's launches
bitwise, and a training-like step after the first launches nothing through the JIT.
"""

from __future__ import annotations

import pytest
import torch
from test_vote_fused import CUDA_ONLY, fused_losses, scene_of_size, targets, to_device

from votesplat_ns.core import triton_launch
from votesplat_ns.core.vote_render import VoteRenderOptions

STREAM = 1234


class StandInCompiled:
    """What the direct path reads of a CompiledKernel: its launcher (``run``), function and packed metadata."""

    def __init__(self, direct_calls):
        self.run = lambda *call: direct_calls.append(call)
        self.function = "function"
        self.packed_metadata = "metadata"


class StandInKernel:
    """A JITFunction as the direct path sees it: ``kernel[grid](*args, **kwargs)`` returns the compiled kernel."""

    def __init__(self):
        self.jit_calls = []
        self.direct_calls = []

        def fn(values, counts, n, scale, BLOCK, FLAG=True):
            pass

        self.fn = fn

    def __getitem__(self, grid):
        def run(*args, **kwargs):
            self.jit_calls.append((grid, args, kwargs))
            return StandInCompiled(self.direct_calls)

        return run


@pytest.fixture
def direct_on_cpu(monkeypatch):
    """The direct path as on CUDA: a supported Triton, device 0, a stand-in stream, no interpreter."""
    monkeypatch.setattr(triton_launch, "_SUPPORTED", True)
    monkeypatch.setattr(triton_launch, "DIRECT", True)
    monkeypatch.setattr(triton_launch, "_get_stream", lambda device: STREAM)
    monkeypatch.setattr(triton_launch, "_hooks_idle", lambda: True)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    monkeypatch.delenv("TRITON_INTERPRET", raising=False)
    monkeypatch.setattr(triton_launch, "_KNOWN", {})


def test_a_known_launch_calls_the_launcher_with_every_parameter(direct_on_cpu):
    kernel = StandInKernel()
    values, counts = torch.zeros(8), torch.zeros(8, dtype=torch.int32)
    triton_launch.launch(kernel, (5,), values, counts, 7, 0.5, BLOCK=32, num_warps=2)
    assert len(kernel.jit_calls) == 1 and kernel.direct_calls == []
    triton_launch.launch(kernel, (6,), values, counts, 9, 0.25, BLOCK=32, num_warps=2)
    assert len(kernel.jit_calls) == 1
    # the runner's call form: grid, stream, function, packed metadata, no launch metadata or hooks, then every
    # parameter in order (the constexpr from the keywords, FLAG from its default; num_warps is no parameter)
    assert kernel.direct_calls == [
        (6, 1, 1, STREAM, "function", "metadata", None, None, None, values, counts, 9, 0.25, 32, True)
    ]


@pytest.mark.parametrize(
    "change",
    ["dtype", "alignment", "int is 1", "int multiple of 16", "int past int32", "float for int", "keyword", "device"],
)
def test_what_triton_specialises_on_goes_through_the_jit(change, direct_on_cpu, monkeypatch):
    kernel = StandInKernel()
    values, counts, n, keywords = torch.zeros(8), torch.zeros(8, dtype=torch.int32), 7, {"BLOCK": 32}
    triton_launch.launch(kernel, (5,), values, counts, n, 0.5, **keywords)
    if change == "dtype":
        values = values.double()
    elif change == "alignment":
        values = torch.zeros(9)[1:]  # 4 bytes past an aligned start
    elif change == "int is 1":
        n = 1
    elif change == "int multiple of 16":
        n = 48
    elif change == "int past int32":
        n = 2**31 + 7
    elif change == "float for int":
        n = 7.0
    elif change == "keyword":
        keywords = {"BLOCK": 64}
    else:
        monkeypatch.setattr(torch.cuda, "current_device", lambda: 1)
    triton_launch.launch(kernel, (5,), values, counts, n, 0.5, **keywords)
    assert len(kernel.jit_calls) == 2 and kernel.direct_calls == []
    triton_launch.launch(kernel, (5,), values, counts, n, 0.5, **keywords)  # now known too
    assert len(kernel.jit_calls) == 2 and len(kernel.direct_calls) == 1


@pytest.mark.parametrize("reason", ["switched off", "interpreter", "launch hook", "unsupported triton"])
def test_the_jit_launches_when_the_direct_path_cannot_be_trusted(reason, direct_on_cpu, monkeypatch):
    kernel = StandInKernel()
    values, counts = torch.zeros(8), torch.zeros(8, dtype=torch.int32)
    triton_launch.launch(kernel, (5,), values, counts, 7, 0.5, BLOCK=32)
    if reason == "switched off":
        monkeypatch.setattr(triton_launch, "DIRECT", False)
    elif reason == "interpreter":
        monkeypatch.setenv("TRITON_INTERPRET", "1")
    elif reason == "launch hook":
        monkeypatch.setattr(triton_launch, "_hooks_idle", lambda: False)
    else:
        monkeypatch.setattr(triton_launch, "_SUPPORTED", False)
    triton_launch.launch(kernel, (5,), values, counts, 7, 0.5, BLOCK=32)
    assert len(kernel.jit_calls) == 2 and kernel.direct_calls == []


def test_a_set_launch_hook_is_seen():
    triton = pytest.importorskip("triton")
    runtime = getattr(getattr(triton, "knobs", None), "runtime", None)
    if runtime is None or not hasattr(getattr(runtime, "launch_enter_hook", None), "add"):
        pytest.skip("this Triton has no HookChain launch hooks")
    assert triton_launch._hooks_idle()

    def hook(metadata):
        pass

    runtime.launch_enter_hook.add(hook)
    try:
        assert not triton_launch._hooks_idle()
    finally:
        runtime.launch_enter_hook.remove(hook)
    assert triton_launch._hooks_idle()


def fused_step(dtype, device):
    """The fused losses' forward, reduction and backward on a test scene: (vote, distortion, the votes' gradient)."""
    scene, level_votes, pixel_xy, lists = scene_of_size(50)
    scene, pixel_xy = to_device(scene, device, dtype), pixel_xy.to(device=device, dtype=dtype)
    target, valid = targets(pixel_xy, 2)
    lists = tuple(t.to(device) for t in lists["gsplat"])
    votes = level_votes[:, :2].to(device=device, dtype=dtype).requires_grad_()
    losses = fused_losses(scene, votes, pixel_xy, target, valid, lists, VoteRenderOptions())
    (2.0 * losses["vote"].sum() + 0.5 * losses["distortion"].sum()).backward()
    return losses["vote"].detach(), losses["distortion"].detach(), votes.grad


@pytest.mark.parametrize("device", CUDA_ONLY)
def test_direct_launches_equal_the_jits(device, monkeypatch):
    from triton.runtime import jit

    jit_runs = []
    run = jit.JITFunction.run

    def counted(self, *args, **kwargs):
        jit_runs.append(self)
        return run(self, *args, **kwargs)

    monkeypatch.setattr(jit.JITFunction, "run", counted)
    monkeypatch.setattr(triton_launch, "_KNOWN", {})
    results = {}
    dtypes = (torch.float32, torch.float64, torch.float32)  # the same constexprs, another dtype between
    for direct in (False, True):
        monkeypatch.setattr(triton_launch, "DIRECT", direct)
        for i, dtype in enumerate(dtypes):
            jit_runs.clear()
            results[direct, i] = fused_step(dtype, device)
            # forward, reduction and backward through the JIT; directly once known (the third step)
            assert len(jit_runs) == (0 if direct and i == 2 else 3)
    for i in range(len(dtypes)):
        (vote, distortion, grad), (vote_direct, distortion_direct, grad_direct) = results[False, i], results[True, i]
        assert torch.equal(vote, vote_direct) and torch.equal(distortion, distortion_direct)  # fixed-order sums
        torch.testing.assert_close(grad, grad_direct)  # the backward's atomic adds land in any order
