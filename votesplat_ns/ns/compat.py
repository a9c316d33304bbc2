"""Small fixes that make nerfstudio 1.1.5 usable offline and under torch >= 2.6.

The checkpoint allow-list is applied on import of the plugin (nerfstudio imports every method
entry point at start-up of ns-train / ns-viewer / ns-export / ns-eval), the others are context
managers around the nerfstudio calls that need them, so users need no environment variable and
no patched nerfstudio. All are listed in :mod:`votesplat_ns.ns.patches`.
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading
import warnings
from pathlib import Path
from typing import Iterator

import numpy as np
import torch

ALEXNET_WEIGHTS = "alexnet-owt-7be5be79.pth"


def register_checkpoint_safe_globals() -> None:
    """Let ``torch.load(weights_only=True)`` read nerfstudio checkpoints.

    torch >= 2.6 defaults to ``weights_only=True``; nerfstudio 1.1.5 calls ``torch.load``
    without the argument and its checkpoints hold numpy scalars (step counters, scheduler
    state), which the restricted unpickler refuses. Allow exactly those numpy types.
    """
    add = getattr(torch.serialization, "add_safe_globals", None)
    if add is None:  # torch < 2.4 loads everything anyway
        return
    numpy_types: list = [np.dtype, np.ndarray]
    try:
        from numpy.core.multiarray import _reconstruct, scalar  # type: ignore[attr-defined]
    except ImportError:  # numpy >= 2 keeps them in numpy._core
        from numpy._core.multiarray import _reconstruct, scalar  # type: ignore[no-redef]
    numpy_types += [scalar, _reconstruct]
    # numpy >= 1.25 pickles dtypes as instances of per-dtype classes (np.dtypes.Float64DType ...)
    dtypes_module = getattr(np, "dtypes", None)
    if dtypes_module is not None:
        numpy_types += [getattr(dtypes_module, name) for name in dir(dtypes_module) if name.endswith("DType")]
    add(numpy_types)


def alexnet_weights_path() -> Path:
    return Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_WEIGHTS


class UnavailableMetric(torch.nn.Module):
    """Stands in for a metric whose weights cannot be had offline; reports NaN."""

    def __init__(self, name: str, reason: str):
        super().__init__()
        self.name = name
        self.reason = reason

    def forward(self, *args, **kwargs) -> torch.Tensor:
        return torch.tensor(float("nan"))


@functools.lru_cache(maxsize=None)
def _warn_once(message: str) -> None:
    warnings.warn(message, RuntimeWarning, stacklevel=3)


def make_lpips_metric() -> torch.nn.Module:
    """splatfacto's LPIPS metric, or an UnavailableMetric when AlexNet is not cached locally.

    torchmetrics downloads torchvision's AlexNet weights when LPIPS is constructed. We never
    start a download: if the weights are not in torch's hub cache, LPIPS is skipped with one
    warning and training/eval carry on. ``VOTESPLAT_ALLOW_DOWNLOADS=1`` restores the download.
    """
    from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

    weights = alexnet_weights_path()
    if not weights.exists() and os.environ.get("VOTESPLAT_ALLOW_DOWNLOADS") != "1":
        reason = f"LPIPS disabled: AlexNet weights not found at {weights} (copy {ALEXNET_WEIGHTS} there to enable it)"
        _warn_once(reason)
        return UnavailableMetric("lpips", reason)
    try:
        return LearnedPerceptualImagePatchSimilarity(normalize=True)
    except Exception as err:  # network or corrupted cache: degrade, do not crash training
        reason = f"LPIPS disabled: {type(err).__name__}: {err}"
        _warn_once(reason)
        return UnavailableMetric("lpips", reason)


@contextlib.contextmanager
def offline_lpips() -> Iterator[None]:
    """Within the block, constructing torchmetrics' LPIPS never touches the network."""
    import torchmetrics.image.lpip as lpip_module

    original = lpip_module.LearnedPerceptualImagePatchSimilarity

    def factory(*args, **kwargs):
        lpip_module.LearnedPerceptualImagePatchSimilarity = original
        try:
            return make_lpips_metric()
        finally:
            lpip_module.LearnedPerceptualImagePatchSimilarity = factory

    lpip_module.LearnedPerceptualImagePatchSimilarity = factory
    try:
        yield
    finally:
        lpip_module.LearnedPerceptualImagePatchSimilarity = original


_cuda_patch_lock = threading.Lock()
_cuda_patch_depth = 0
_original_tensor_cuda = torch.Tensor.cuda


def _tensor_stays_put(self: torch.Tensor, *args, **kwargs) -> torch.Tensor:
    return self


@contextlib.contextmanager
def cuda_calls_stay_on_cpu(model_on_cpu: bool = False) -> Iterator[None]:
    """Make ``Tensor.cuda()`` a no-op inside the block when no CUDA device exists, or always when
    ``model_on_cpu`` (a model kept on the CPU of a CUDA machine, e.g. ``--machine.device-type cpu``).

    splatfacto hard-codes ``.cuda()`` in ``populate_modules`` and ``get_outputs``; on a CPU-only
    machine we run its code unchanged (rather than copying it) and keep tensors where they are.
    Reference-counted under a lock because the viewer renders from another thread while
    training runs: the real method comes back only when the last block exits.
    """
    global _cuda_patch_depth
    if torch.cuda.is_available() and not model_on_cpu:
        yield
        return
    with _cuda_patch_lock:
        _cuda_patch_depth += 1
        torch.Tensor.cuda = _tensor_stays_put  # type: ignore[method-assign]
    try:
        yield
    finally:
        with _cuda_patch_lock:
            _cuda_patch_depth -= 1
            if _cuda_patch_depth == 0:
                torch.Tensor.cuda = _original_tensor_cuda  # type: ignore[method-assign]
