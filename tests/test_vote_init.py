"""The lifted start of the retrofit's vote offsets (votesplat_ns/core/vote_init.py)."""

import math

import numpy as np
import torch

from votesplat_ns.core.cameras import PinholeView
from votesplat_ns.core.mask_consensus import seen_pixels
from votesplat_ns.core.rasterize_torch import rasterize_torch
from votesplat_ns.core.vote_init import lifted_votes, point_on_ray
from votesplat_ns.core.vote_maps import VoteMaps, mask_centroids, to_continuous
from votesplat_ns.core.vote_render import project_to_pixels

WIDTH, HEIGHT = 64, 48
K = torch.tensor([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])


def look_at(position, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """World-to-camera [4, 4], OpenCV axes (x right, y down, z towards ``target``)."""
    position, target, up = (np.asarray(v, dtype=np.float64) for v in (position, target, up))
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    viewmat = np.eye(4)
    viewmat[:3, :3] = np.stack([right, down, forward])
    viewmat[:3, 3] = -viewmat[:3, :3] @ position
    return torch.tensor(viewmat, dtype=torch.float32)


def ring_views(count, radius=4.0, height=0.5):
    return [
        PinholeView(
            look_at((radius * math.cos(a), radius * math.sin(a), height)), K.clone(), WIDTH, HEIGHT, name=f"v{i}"
        )
        for i, a in enumerate(np.linspace(0, 2 * math.pi, count, endpoint=False))
    ]


def gaussians(points, scale=0.06):
    means = torch.tensor(np.asarray(points), dtype=torch.float32)
    n = means.shape[0]
    return means, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n, 3), scale), torch.full((n,), 0.99)


def blob_masks(view, means, quats, scales, opacities, members):
    """Label image: 1 where the ``members`` Gaussians cover the pixel (the object's mask), else 0."""
    _, alpha, _ = rasterize_torch(
        means[members],
        quats[members],
        scales[members],
        opacities[members],
        torch.zeros(int(members.sum()), 3),
        view.viewmat[None],
        view.K[None],
        view.width,
        view.height,
        sh_degree=None,
    )
    return (alpha[0, ..., 0] > 0.5).numpy().astype(np.int32)


def vote_maps_for(views, scene, members, levels=1):
    maps = []
    for view in views:
        labels, centroids = mask_centroids(blob_masks(view, *scene, members))
        maps.append(VoteMaps(np.stack([labels] * levels).astype(np.int32), [centroids] * levels))
    return maps


def test_point_on_ray_inverts_the_projection():
    view = ring_views(3)[1]
    K_skew = view.K.clone()
    K_skew[0, 1] = 3.0
    pixels = torch.tensor([[10.5, 7.25], [40.0, 30.0], [32.0, 24.0]], dtype=torch.float64)
    depth = torch.tensor([1.0, 2.5, 7.0], dtype=torch.float64)
    points = point_on_ray(pixels, depth, view.viewmat.double(), K_skew.double())
    assert torch.allclose(project_to_pixels(points, view.viewmat.double(), K_skew.double()), pixels, atol=1e-9)
    assert torch.allclose(points @ view.viewmat.double()[2, :3] + view.viewmat.double()[2, 3], depth, atol=1e-9)


def test_lifted_votes_land_on_the_blob_centre_and_unseen_gaussians_keep_zero():
    rng = np.random.default_rng(0)
    centre = np.array([0.3, -0.2, 0.1])
    blob = centre + rng.normal(0, 0.12, size=(300, 3))
    backdrop = np.array([2.5, 2.5, 0.0]) + rng.normal(0, 0.05, size=(40, 3))  # seen, in no mask
    far_away = np.array([[0.0, 0.0, -60.0], [0.0, 0.0, 60.0]])  # in no view (straight below and above)
    scene = gaussians(np.concatenate([blob, backdrop, far_away]))
    members = torch.zeros(scene[0].shape[0], dtype=torch.bool)
    members[:300] = True
    views = ring_views(8)
    maps = vote_maps_for(views, scene, members, levels=2)
    result = lifted_votes(rasterize_torch, *scene, views, maps)
    offsets, count = result.offsets, result.views
    assert offsets.shape == (342, 2, 3) and count.shape == (342, 2)
    assert torch.equal(offsets[:, 0], offsets[:, 1]) and torch.equal(count[:, 0], count[:, 1])
    votes = scene[0][:, None, :] + offsets
    seen = count[:300, 0] > 0
    assert seen.float().mean() > 0.3  # the blob's surface, from several sides
    start = np.linalg.norm(blob[seen.numpy()] - centre, axis=-1).mean()
    error = (votes[:300][seen, 0] - torch.tensor(centre, dtype=torch.float32)).norm(dim=-1)
    # the seen blob Gaussians now vote near the centre: in 3D about half as far as they sit (what
    # is left lies mostly along the rays of the few views that see each one) ...
    assert error.mean() < 0.6 * start and error.max() < 2 * start, (error.mean(), error.max(), start)
    # ... and in every view their votes project a third as far from the mask's centroid (the vote loss)
    for view, m in zip(views, maps):
        pixels = torch.tensor(seen_pixels(rasterize_torch, *[t[:300] for t in scene], view) >= 0)
        target = torch.tensor(to_continuous(m.centroids[0][1]))
        before = (project_to_pixels(scene[0][:300][pixels], view.viewmat, view.K) - target).norm(dim=-1).mean()
        after = (project_to_pixels(votes[:300, 0][pixels], view.viewmat, view.K) - target).norm(dim=-1).mean()
        assert after < 0.5 * before, (view.name, after, before)
    assert (offsets[:300][~seen] == 0).all()
    # the backdrop is seen, but in no mask; the far Gaussians are in no view: both keep 0
    assert any((seen_pixels(rasterize_torch, *[t[300:340] for t in scene], view) >= 0).any() for view in views)
    assert (offsets[300:] == 0).all() and (count[300:] == 0).all()


def test_one_view_reproduces_its_mask_centroid_exactly():
    # blend then project: the lifted votes of one view all lie on the ray through the mask's
    # centroid, so they (and any mean of them) project onto that centroid
    rng = np.random.default_rng(1)
    scene = gaussians(rng.normal(0, 0.2, size=(200, 3)))
    members = torch.ones(200, dtype=torch.bool)
    views = ring_views(5)[2:3]
    maps = vote_maps_for(views, scene, members)
    result = lifted_votes(rasterize_torch, *scene, views, maps)
    seen = result.views[:, 0] > 0
    assert seen.sum() > 20
    votes = scene[0] + result.offsets[:, 0]
    target = torch.tensor(to_continuous(maps[0].centroids[0][1]))
    projected = project_to_pixels(votes[seen], views[0].viewmat, views[0].K)
    assert torch.allclose(projected, target.expand_as(projected), atol=1e-3)
    assert torch.allclose(project_to_pixels(votes[seen].mean(0), views[0].viewmat, views[0].K), target, atol=1e-3)
    # each lifted vote kept its Gaussian's camera depth
    depth = lambda p: p @ views[0].viewmat[2, :3] + views[0].viewmat[2, 3]  # noqa: E731
    assert torch.allclose(depth(votes[seen]), depth(scene[0][seen]), atol=1e-4)


def test_masks_without_a_vote_target_give_no_lifted_point():
    scene = gaussians(np.random.default_rng(2).normal(0, 0.2, size=(100, 3)))
    views = ring_views(4)
    maps = vote_maps_for(views, scene, torch.ones(100, dtype=torch.bool))
    for m in maps:
        m.centroids[0][1:] = np.nan  # border_masks="mask_only": a mask but no vote
    result = lifted_votes(rasterize_torch, *scene, views, maps)
    assert (result.offsets == 0).all() and (result.views == 0).all()
