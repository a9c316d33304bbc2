"""Triton launches without the JIT's per-call dispatch: the vote kernels' launches are small and many.

``kernel[grid](*args)`` binds and specialises every argument, builds the cache key, looks the compiled kernel
up, builds launch metadata for the launch hooks and only then calls the compiled kernel's launcher. On the
H100's host that is 54 us for the fused forward (31 arguments), 27 us for the reduction and 50 us for the
backward, of which calling the launcher directly takes 16, 10 and 15 us (BENCHMARKS.md, "Fused vote kernels");
a training vote step makes three such launches, and inside a training step every host call costs two to three
times what it does in a loop.

``launch`` remembers, per kernel, the compiled kernels the JIT returned, under a key of its own that
separates at least what Triton's specialisation separates: the keyword arguments (the constexprs and
options such as ``num_warps``), the current device, and per positional argument its class, a tensor's dtype
and 16-byte alignment, an int's Triton type (by range) and whether it is 1 or a multiple of 16 (a kernel
that does not specialise on them gets a few keys for one compiled kernel, which costs nothing). A known key
calls the launcher with the arguments ``CompiledKernel.__getitem__``'s runner passes (grid, stream,
function, packed metadata, no launch metadata and no hooks, then every parameter in order, constexprs
included); an unknown key launches through ``kernel[grid]``, which finds or compiles the kernel, and is then
known.

The JIT's own path is taken whenever the direct one is not known to be what it does: under Triton's
interpreter, outside Triton 3.6-3.x (the launcher's call form: run on 3.6 by the GPU tests, read in 3.8's
source; older versions were not checked), or while a launch hook is set (a profiler such as proton hooks every launch). What it does not look at: Triton's debug and
instrumentation settings, which the JIT reads from its knobs on every call; change them before the first
launch of a process, not between launches.
"""

from __future__ import annotations

import inspect
import os
from typing import Any, Callable, Dict, Optional, Tuple

import torch
from torch import Tensor

try:  # optional: the torch path works without it
    import triton
except ImportError:  # pragma: no cover - depends on the environment
    triton = None

# False sends every launch through kernel[grid] (tests compare the two; an A/B can switch it).
DIRECT = True

_INT32 = range(-(2**31), 2**31)
_INT64 = range(-(2**63), 2**63)


def _supported_version() -> bool:
    if triton is None:
        return False
    try:
        major, minor = (int(part) for part in triton.__version__.split(".")[:2])
    except ValueError:
        return False
    return major == 3 and minor >= 6


_SUPPORTED = _supported_version()


class _Known:
    """A compiled kernel as the direct path calls it."""

    __slots__ = ("launcher", "function", "packed_metadata", "tail")

    def __init__(self, compiled: Any, tail: Tuple[Any, ...]):
        self.launcher: Callable = compiled.run  # made at the JIT's launch (its handles are loaded)
        self.function = compiled.function
        self.packed_metadata = compiled.packed_metadata
        self.tail = tail  # the parameters after the positional arguments, in order: keywords or defaults


# kernel -> {key -> _Known}
_KNOWN: Dict[Any, Dict[Tuple, _Known]] = {}
_get_stream: Optional[Callable[[int], int]] = None


def _int_key(value: int) -> Tuple[bool, bool, int]:
    # Triton types an int i32, i64 or u64 by its range, and specialises on == 1 and on % 16 == 0
    width = 0 if value in _INT32 else 1 if value in _INT64 else 2
    return value == 1, value % 16 == 0, width


def _arg_key(args: Tuple[Any, ...]) -> Tuple:
    return tuple(
        [
            (a.dtype, a.data_ptr() % 16 == 0) if isinstance(a, Tensor) else _int_key(a) if type(a) is int else type(a)
            for a in args
        ]
    )


def _hooks_idle() -> bool:
    """No launch hook to call: None, or a HookChain without calls."""
    runtime = getattr(getattr(triton, "knobs", None), "runtime", None)
    if runtime is None:
        return False
    for hook in (getattr(runtime, "launch_enter_hook", None), getattr(runtime, "launch_exit_hook", None)):
        if hook is not None and getattr(hook, "calls", True):
            return False
    return True


def direct_possible() -> bool:
    return DIRECT and _SUPPORTED and os.environ.get("TRITON_INTERPRET", "0") != "1" and _hooks_idle()


def launch(kernel, grid: Tuple[int, ...], *args, **kwargs) -> None:
    """``kernel[grid](*args, **kwargs)`` for a CUDA launch on the current device and stream."""
    if not direct_possible():
        kernel[grid](*args, **kwargs)
        return
    device = torch.cuda.current_device()
    key = (device, tuple(kwargs.items()), _arg_key(args))
    known = _KNOWN.get(kernel, {}).get(key)
    if known is None:
        compiled = kernel[grid](*args, **kwargs)
        _remember(kernel, key, compiled, len(args), kwargs)
        return
    grid_x, grid_y, grid_z = (tuple(grid) + (1, 1))[:3]
    known.launcher(
        grid_x,
        grid_y,
        grid_z,
        _current_stream(device),
        known.function,
        known.packed_metadata,
        None,
        None,
        None,
        *args,
        *known.tail,
    )


def _current_stream(device: int) -> int:
    """The raw current stream, as the JIT gets it (Triton's driver hands out torch's)."""
    global _get_stream
    if _get_stream is None:
        _get_stream = triton.runtime.driver.active.get_current_stream  # type: ignore[union-attr]
    return _get_stream(device)  # type: ignore[misc]


def _remember(kernel, key: Tuple, compiled: Any, positional: int, kwargs: Dict[str, Any]) -> None:
    if not all(hasattr(compiled, name) for name in ("run", "function", "packed_metadata")):
        return  # not a CompiledKernel as the direct path knows it: this key keeps the JIT's path
    parameters = list(inspect.signature(kernel.fn).parameters.values())[positional:]
    if any(p.name not in kwargs and p.default is inspect.Parameter.empty for p in parameters):
        return
    tail = tuple(kwargs[p.name] if p.name in kwargs else p.default for p in parameters)
    _KNOWN.setdefault(kernel, {})[key] = _Known(compiled, tail)
