"""Masks as the LERF-OVS protocol compares them: bool checks, the rendered silhouette's threshold, IoU."""

from __future__ import annotations

from typing import Any

import numpy as np

try:  # torch is optional here: predictions may be numpy arrays or tensors.
    import torch
except ImportError:  # pragma: no cover - torch is a project dependency
    torch = None


# OpenGaussian thresholds the rendered silhouette (accumulated opacity) of the selected Gaussians at 0.7.
SILHOUETTE_THRESHOLD = 0.7


def _to_numpy(array: Any) -> np.ndarray:
    if torch is not None and isinstance(array, torch.Tensor):
        return array.detach().cpu().numpy()
    return np.asarray(array)


def as_bool_mask(mask: Any, what: str) -> np.ndarray:
    mask = _to_numpy(mask)
    if mask.ndim != 2:
        raise ValueError(f"{what} must be [H, W], got shape {mask.shape}")
    if mask.dtype == bool:
        return mask
    if np.issubdtype(mask.dtype, np.integer) and np.isin(mask, (0, 1)).all():
        return mask.astype(bool)
    raise ValueError(
        f"{what} has dtype {mask.dtype}; pass a bool (or 0/1) mask, e.g. threshold the rendered "
        f"accumulated opacity with silhouette_mask(acc, {SILHOUETTE_THRESHOLD})"
    )


def silhouette_mask(accumulation: Any, threshold: float = SILHOUETTE_THRESHOLD) -> np.ndarray:
    """Bool mask from the accumulated opacity [H, W] (or [H, W, 1]) rendered for the selected Gaussians."""
    accumulation = _to_numpy(accumulation).astype(np.float64)
    if accumulation.ndim == 3 and accumulation.shape[-1] == 1:
        accumulation = accumulation[..., 0]
    if accumulation.ndim != 2:
        raise ValueError(f"accumulation must be [H, W] or [H, W, 1], got shape {accumulation.shape}")
    if not np.isfinite(accumulation).all():
        raise ValueError("accumulation has non-finite values; check the render")
    return accumulation > threshold


def mask_iou(predicted: Any, ground_truth: Any) -> float:
    """IoU of two bool masks of equal shape; 0 when both are empty (OpenGaussian's rule)."""
    predicted = as_bool_mask(predicted, "predicted mask")
    ground_truth = as_bool_mask(ground_truth, "ground-truth mask")
    if predicted.shape != ground_truth.shape:
        raise ValueError(
            f"predicted mask is {predicted.shape[1]}x{predicted.shape[0]} but the label is "
            f"{ground_truth.shape[1]}x{ground_truth.shape[0]}; render at the label resolution (scale the intrinsics)"
        )
    union = np.logical_or(predicted, ground_truth).sum()
    if union == 0:
        return 0.0
    return float(np.logical_and(predicted, ground_truth).sum() / union)
