"""splatfacto's image metrics built at their first call, and its LPIPS without a download.

:func:`votesplat_ns.ns.patches.metrics_at_first_use` makes splatfacto's ``populate_modules`` build its PSNR and
LPIPS as :class:`MetricAtFirstUse`, the LPIPS through :func:`make_lpips_metric`; every patch of upstream code
lives in :mod:`votesplat_ns.ns.patches`.
"""

from __future__ import annotations

import functools
import os
import warnings
from pathlib import Path
from typing import Callable, Optional

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
    weights = alexnet_weights_path()
    if not weights.exists() and os.environ.get("VOTESPLAT_ALLOW_DOWNLOADS") != "1":
        reason = f"LPIPS disabled: AlexNet weights not found at {weights} (copy {ALEXNET_WEIGHTS} there to enable it)"
        _warn_once(reason)
        return UnavailableMetric("lpips", reason)
    from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

    try:
        return LearnedPerceptualImagePatchSimilarity(normalize=True)
    except Exception as err:  # network or corrupted cache: degrade, do not crash training
        reason = f"LPIPS disabled: {type(err).__name__}: {err}"
        _warn_once(reason)
        return UnavailableMetric("lpips", reason)


class MetricAtFirstUse(torch.nn.Module):
    """One of splatfacto's image metrics (PSNR, LPIPS), built by ``build`` at its first call.

    Building one imports torchmetrics, whose package import loads every metric it has (``transformers`` too, where
    it is installed), in every process that builds a model, each rank of a run of several included: 1.4 s on the
    2-core development machine; without it a retrofit's set-up on an H200 host is 1.6 s shorter (BENCHMARKS.md,
    "Several GPUs"). A retrofit's vote-only steps, ``ns-export``, ``ns-viewer`` and ``votesplat click`` / ``query`` /
    ``eval`` never call these metrics, so they never pay for them; colour training pays at its first step's PSNR,
    as before at set-up.

    The built metric is not a submodule: its weights (LPIPS's AlexNet) are constant, so they stay out of the
    checkpoint and out of DistributedDataParallel's parameters. It follows its inputs' device instead.
    """

    def __init__(self, build: Callable[[], torch.nn.Module]):
        super().__init__()
        self.build = build
        self._metric: Optional[torch.nn.Module] = None
        self._device: Optional[torch.device] = None

    @property
    def built(self) -> Optional[torch.nn.Module]:
        """The metric, once a call has built it."""
        return self._metric

    def forward(self, *args, **kwargs):
        device = next((arg.device for arg in args if isinstance(arg, torch.Tensor)), torch.device("cpu"))
        if self._metric is None:
            # object.__setattr__: torch.nn.Module's would register the metric as a submodule
            object.__setattr__(self, "_metric", self.build())
        if device != self._device:
            self._metric.to(device)  # type: ignore[union-attr]
            self._device = device
        return self._metric(*args, **kwargs)  # type: ignore[misc]
