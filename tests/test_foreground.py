"""Foreground by rendering weight (votesplat_ns.core.foreground) against a forward-only reference."""

import math

import pytest
import torch

from votesplat_ns.core.foreground import foreground_from_exposure, mask_exposure
from votesplat_ns.core.rasterize_torch import rasterize_torch

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
    render, _, _ = rasterize_torch(
        means, quats, scales, opacities, torch.eye(n, dtype=means.dtype), viewmat[None], K[None], WIDTH, HEIGHT
    )
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


def test_object_cut_by_the_frame_in_all_views_but_one_stays_foreground():
    """A large object touching the image border in every view but one: border masks must not make it background."""
    import numpy as np

    from votesplat_ns.core.clustering import cluster_levels
    from votesplat_ns.core.vote_maps import mask_centroids

    generator = torch.Generator().manual_seed(5)
    # a 2 x 1.6 slab of small opaque Gaussians in front of the camera, at depth 4 +- 0.3
    n = 400
    means = torch.rand(n, 3, generator=generator, dtype=torch.float64) * torch.tensor(
        [2.0, 1.6, 0.6], dtype=torch.float64
    )
    means -= torch.tensor([1.0, 0.8, -3.7], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64).repeat(n, 1)
    scales = torch.full((n, 3), 0.08, dtype=torch.float64)
    opacities = torch.full((n,), 0.9, dtype=torch.float64)
    scene = (means, quats, scales, opacities)
    views, touching = [], []
    for yaw in (0.0, 0.3, -0.3, 0.45, -0.45):
        viewmat, K = camera(yaw)
        K = K.clone()
        # the first view sees the whole slab; the others are zoomed in so that it overflows the frame
        K[0, 0] = K[1, 1] = 12.0 if yaw == 0.0 else 40.0
        alpha = rasterize_torch(*scene, torch.ones(n, 1, dtype=torch.float64), viewmat[None], K[None], WIDTH, HEIGHT)[
            1
        ][0, ..., 0]
        object_mask = (alpha > 0.5).numpy().astype(np.int32)
        views.append((viewmat, K, object_mask))
        touching.append(
            bool(object_mask[0].any() or object_mask[-1].any() or object_mask[:, 0].any() or object_mask[:, -1].any())
        )
    assert touching == [False, True, True, True, True]

    def foreground_share(rule: str) -> float:
        rule_views = [(v, k, torch.from_numpy(mask_centroids(m, rule)[0])[None]) for v, k, m in views]
        return float(foreground_from_exposure(mask_exposure(rasterize_torch, *scene, rule_views))[:, 0].double().mean())

    assert foreground_share("drop") < 0.5  # the old rule: the slab is mostly background
    for rule in ("vote", "mask_only"):
        share = foreground_share(rule)
        assert share > 0.95, (rule, share)
    # foreground Gaussians whose votes reached the slab's centre are one instance (beside a second object:
    # HDBSCAN never returns a single cluster)
    rng = np.random.default_rng(0)
    other = rng.uniform([4.0, 0.0, 3.0], [4.5, 0.5, 3.5], size=(200, 3))
    all_means = np.concatenate([means.numpy(), other])
    centres = np.concatenate([np.tile([0.0, 0.0, 4.0], (n, 1)), np.tile([4.25, 0.25, 3.25], (200, 1))])
    offsets = (centres - all_means + rng.normal(0.0, 0.01, all_means.shape))[:, None, :]
    instances = cluster_levels(all_means, offsets, np.ones((n + 200, 1)), ("instance",))
    slab_ids = instances.level(0).ids[:n]
    assert instances.level(0).num_instances == 2 and (slab_ids >= 0).all() and len(set(slab_ids)) == 1
