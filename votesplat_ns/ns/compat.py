"""splatfacto's LPIPS metric without a download: the local AlexNet weights, or a NaN-reporting stand-in.

:func:`votesplat_ns.ns.patches.offline_lpips` makes nerfstudio build its LPIPS through
:func:`make_lpips_metric`; every patch of upstream code lives in :mod:`votesplat_ns.ns.patches`.
"""

from __future__ import annotations

import functools
import os
import warnings
from pathlib import Path

import torch

ALEXNET_WEIGHTS = "alexnet-owt-7be5be79.pth"


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
