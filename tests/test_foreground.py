"""Foreground by rendering weight (votesplat_ns.foreground) against a forward-only reference."""

import math

import pytest
import torch

from votesplat_ns.foreground import foreground_from_exposure, mask_exposure
from votesplat_ns.rasterize_torch import rasterize_torch

WIDTH, HEIGHT = 24, 20


def random_scene(n: int, seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=generator) * torch.tensor([2.0, 2.0, 1.0]) - torch.tensor([1.0, 1.0, -3.0])
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=generator), dim=-1)
    scales = torch.rand(n, 3, generator=generator) * 0.2 + 0.05
    opacities = torch.rand(n, generator=generator) * 0.9 + 0.05
    return means.double(), quats.double(), scales.double(), opacities.double()


def camera(yaw: float):
    c, s = math.cos(yaw), math.sin(yaw)
    rotation = torch.tensor([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]], dtype=torch.float64)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = rotation
    viewmat[:3, 3] = torch.tensor([0.0, 0.0, 4.0]) - rotation @ torch.tensor([0.0, 0.0, 4.0], dtype=torch.float64)
    K = torch.tensor([[30.0, 0.0, WIDTH / 2], [0.0, 30.0, HEIGHT / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return viewmat, K


def per_gaussian_weights(scene, viewmat, K):
    """[H, W, N] alpha*T of every Gaussian at every pixel: one one-hot colour channel per Gaussian."""
    means, quats, scales, opacities = scene
    n = means.shape[0]
    render, _, _ = rasterize_torch(means, quats, scales, opacities, torch.eye(n, dtype=means.dtype), viewmat[None], K[None], WIDTH, HEIGHT)
    return render[0]


def test_exposure_is_each_gaussians_weight_inside_and_outside_the_masks():
    scene = random_scene(30)
    generator = torch.Generator().manual_seed(1)
    views = []
    expected = torch.zeros(30, 2, 2, dtype=torch.float64)
    for yaw in (-0.2, 0.0, 0.25):
        viewmat, K = camera(yaw)
        labels = torch.randint(0, 3, (2, HEIGHT, WIDTH), generator=generator)
        views.append((viewmat, K, labels))
        weights = per_gaussian_weights(scene, viewmat, K)  # [H, W, N]
        for level in range(2):
            inside = (labels[level] > 0).to(weights.dtype)[..., None]
            expected[:, level, 0] += (weights * inside).sum(dim=(0, 1))
            expected[:, level, 1] += (weights * (1 - inside)).sum(dim=(0, 1))
    exposure = mask_exposure(rasterize_torch, *scene, views)
    assert exposure.shape == (30, 2, 2)
    assert expected.sum() > 1.0  # the scene is in view
    torch.testing.assert_close(exposure, expected, rtol=1e-9, atol=1e-12)


def test_gaussians_seen_mostly_outside_the_masks_are_background():
    # a Gaussian left of centre and one right of centre; the mask covers only the left half
    means = torch.tensor([[-0.6, 0.0, 4.0], [0.6, 0.0, 4.0]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, dtype=torch.float64)
    scales = torch.full((2, 3), 0.1, dtype=torch.float64)
    opacities = torch.tensor([0.9, 0.9], dtype=torch.float64)
    viewmat, K = torch.eye(4, dtype=torch.float64), camera(0.0)[1]
    labels = torch.zeros(1, HEIGHT, WIDTH, dtype=torch.long)
    labels[0, :, : WIDTH // 2] = 1
    exposure = mask_exposure(rasterize_torch, means, quats, scales, opacities, [(viewmat, K, labels)])
    assert foreground_from_exposure(exposure)[:, 0].tolist() == [True, False]


def test_foreground_rule_and_bad_input():
    exposure = torch.tensor([[[3.0, 1.0]], [[1.0, 3.0]], [[0.0, 0.0]], [[1.0, 1.0]]])
    assert foreground_from_exposure(exposure)[:, 0].tolist() == [True, False, False, False]  # unseen: background
    assert foreground_from_exposure(exposure, 0.2)[:, 0].tolist() == [True, True, False, True]
    with pytest.raises(ValueError, match="min_masked_share"):
        foreground_from_exposure(exposure, 1.0)
    scene = random_scene(3)
    with pytest.raises(ValueError, match="no views"):
        mask_exposure(rasterize_torch, *scene, [])
    with pytest.raises(ValueError, match=r"\[L, H, W\]"):
        mask_exposure(rasterize_torch, *scene, [(*camera(0.0), torch.zeros(HEIGHT, WIDTH))])
