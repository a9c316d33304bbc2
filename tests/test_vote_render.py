"""Tests for votesplat_ns.core.vote_render (paper section 3.3)."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from gsplat.cuda._torch_impl import (
    _fully_fused_projection,
    _isect_offset_encode,
    _isect_tiles,
    _quat_scale_to_covar_preci,
)
from torch.overrides import TorchFunctionMode

from votesplat_ns.core import vote_render
from votesplat_ns.core.vote_render import (
    ALPHA_MIN,
    COLOUR_STOP_T,
    VOTE_THRESHOLD_RTOL,
    VoteRender,
    VoteRenderOptions,
    project_to_pixels,
    render_votes_reference,
    render_votes_tiled,
    vote_losses,
)


@pytest.fixture(autouse=True, scope="module")
def single_thread():
    """These tensors are tiny: intra-op threads only add synchronisation, badly so on a busy 2-core runner."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


CUDA_PARAM = pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"))


# ---------------------------------------------------------------------------
# Scene helpers


def look_at(eye, target, dtype=torch.float64):
    """OpenCV world-to-camera matrix looking from eye at target (world z up)."""
    eye = torch.tensor(eye, dtype=dtype)
    target = torch.tensor(target, dtype=dtype)
    forward = target - eye
    forward = forward / forward.norm()
    up = torch.tensor([0.0, 0.0, 1.0], dtype=dtype)
    right = torch.linalg.cross(forward, up)
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    rotation = torch.stack([right, down, forward])
    viewmat = torch.eye(4, dtype=dtype)
    viewmat[:3, :3] = rotation
    viewmat[:3, 3] = -rotation @ eye
    return viewmat


def intrinsics(focal, width, height, dtype=torch.float64):
    return torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)


def project_gaussians(means, quats, scales, viewmat, K, width, height):
    """Project 3D Gaussians to one camera with gsplat's pure-torch reference."""
    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_preci=False)
    radii, means2d, depths, conics, _ = _fully_fused_projection(means, covars, viewmat[None], K[None], width, height)
    return means2d[0], conics[0], depths[0], radii[0]


def random_scene(n, width, height, seed, dtype=torch.float64):
    """Random Gaussians in front of a camera, with overlap and a spread of opacities."""
    g = torch.Generator().manual_seed(seed)
    viewmat = look_at([0.3, -4.0, 0.5], [0.0, 0.0, 0.0], dtype)
    K = intrinsics(0.9 * width, width, height, dtype)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * torch.tensor([2.6, 2.0, 2.0], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = 0.1 + 0.3 * torch.rand(n, 3, generator=g, dtype=dtype)
    opacities = torch.rand(n, generator=g, dtype=dtype)
    opacities[: n // 5] = 0.995  # clamped to alpha_max at their centres
    means2d, conics, depths, _ = project_gaussians(means, quats, scales, viewmat, K, width, height)
    votes = means + 0.4 * torch.randn(n, 3, generator=g, dtype=dtype)
    return dict(means2d=means2d, conics=conics, opacities=opacities, depths=depths, votes=votes, viewmat=viewmat, K=K)


def pixel_centres(width, height, dtype=torch.float64):
    ys, xs = torch.meshgrid(torch.arange(height, dtype=dtype), torch.arange(width, dtype=dtype), indexing="ij")
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=1) + 0.5


def sample_pixels(width, height, seed, extra=40, dtype=torch.float64):
    """All pixel centres plus off-centre continuous positions."""
    g = torch.Generator().manual_seed(seed)
    off_centre = torch.rand(extra, 2, generator=g, dtype=dtype) * torch.tensor([width, height], dtype=dtype)
    return torch.cat([pixel_centres(width, height, dtype), off_centre])


def conservative_radii(conics, opacities):
    """Distance beyond which alpha < 1/255 everywhere: sigma >= |d|^2 / (2 lambda_max(cov2d))."""
    a, b, c = conics.unbind(-1)
    smallest_conic_eigen = (a + c) / 2 - torch.sqrt(((a - c) / 2) ** 2 + b**2)
    log_ratio = torch.log((255.0 * opacities).clamp_min(1.0))
    return torch.sqrt(2.0 * log_ratio / smallest_conic_eigen) * 1.01 + 1.0


def tile_lists_gsplat(scene, width, height, tile_size):
    """gsplat's own (pure-torch) isect_tiles / isect_offset_encode, fed radii that cover every alpha >= 1/255."""
    tiles_wide, tiles_high = math.ceil(width / tile_size), math.ceil(height / tile_size)
    radii = conservative_radii(scene["conics"], scene["opacities"]).float()
    _, isect_ids, flatten_ids = _isect_tiles(
        scene["means2d"][None].float(), radii[None], scene["depths"][None].float(), tile_size, tiles_wide, tiles_high
    )
    offsets = _isect_offset_encode(isect_ids, 1, tiles_wide, tiles_high)
    return offsets, flatten_ids


def tile_lists_everything(scene, width, height, tile_size):
    """Every Gaussian in every tile, front to back."""
    tiles_wide, tiles_high = math.ceil(width / tile_size), math.ceil(height / tile_size)
    n = scene["depths"].shape[0]
    order = torch.argsort(scene["depths"], stable=True).int()
    flatten_ids = order.repeat(tiles_wide * tiles_high)
    offsets = (torch.arange(tiles_high * tiles_wide, dtype=torch.int32) * n).reshape(tiles_high, tiles_wide)
    return offsets, flatten_ids


def scene_to(scene, device, dtype=None):
    return {k: v.to(device=device, dtype=dtype or v.dtype) for k, v in scene.items()}


def call(render_fn, scene, pixel_xy, options, **kwargs):
    return render_fn(
        scene["means2d"],
        scene["conics"],
        scene["opacities"],
        scene["depths"],
        scene["votes"],
        scene["viewmat"],
        scene["K"],
        pixel_xy,
        options=options,
        **kwargs,
    )


# ---------------------------------------------------------------------------
# Literal brute force: one pixel at a time, one Gaussian at a time, python floats


def brute_force_walk(scene, pixel_xy, threshold, alpha_max):
    """Per pixel: the voting set in walk order, with each member's (uniform, alpha*T) weight."""
    means2d = scene["means2d"].tolist()
    conics = scene["conics"].tolist()
    opacities = scene["opacities"].tolist()
    depths = scene["depths"].tolist()
    threshold = threshold * (1.0 + VOTE_THRESHOLD_RTOL)
    order = sorted(range(len(depths)), key=lambda i: (depths[i], i))
    walks = []
    for px, py in pixel_xy.tolist():
        transmittance = 1.0
        members = []
        for i in order:
            dx, dy = means2d[i][0] - px, means2d[i][1] - py
            a, b, c = conics[i]
            sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
            if sigma < 0:
                continue
            alpha = min(alpha_max, opacities[i] * math.exp(-sigma))
            if alpha < 1.0 / 255.0:
                continue
            next_t = transmittance * (1.0 - alpha)
            if next_t <= 1e-4:
                break
            if transmittance > threshold:
                members.append((i, {"uniform": 1.0, "alpha_t": alpha * transmittance}))
            transmittance = next_t
        walks.append(members)
    return walks


_WALKS = {}


def brute_force(scene, pixel_xy, options):
    key = (id(scene), id(pixel_xy), options.vote_transmittance, options.alpha_max)
    if key not in _WALKS:
        _WALKS[key] = brute_force_walk(scene, pixel_xy, options.vote_transmittance, options.alpha_max)
    votes = scene["votes"].tolist()
    viewmat = scene["viewmat"].tolist()
    K = scene["K"].tolist()

    def to_camera(point):
        return [sum(viewmat[r][c] * point[c] for c in range(3)) + viewmat[r][3] for r in range(3)]

    def to_pixels(point):
        x, y, z = to_camera(point)
        z = max(z, options.vote_near_plane)
        return [K[0][0] * x / z + K[0][1] * y / z + K[0][2], K[1][1] * y / z + K[1][2]]

    counts, mean_votes, projected, distortions = [], [], [], []
    for walk in _WALKS[key]:
        members = [i for i, _ in walk]
        weights = [w[options.weighting] for _, w in walk]
        m = len(members)
        counts.append(m)
        if m == 0:
            mean_votes.append([0.0] * 3)
            projected.append([0.0] * 2)
            distortions.append(0.0)
            continue
        total = sum(weights)
        mean_vote = [sum(w * votes[i][k] for w, i in zip(weights, members)) / total for k in range(3)]
        mean_votes.append(mean_vote)
        if options.blend_space == "3d":
            projected.append(to_pixels(mean_vote))
        else:
            points = [to_pixels(votes[i]) for i in members]
            projected.append([sum(w * pt[k] for w, pt in zip(weights, points)) / total for k in range(2)])
        z = [to_camera(votes[i])[2] for i in members]
        pairs = [(z[i], z[j]) for i in range(m) for j in range(i + 1, m)]
        if options.distortion == "l1":
            distortions.append(sum(abs(zi - zj) for zi, zj in pairs))
        elif options.distortion == "l1_pixels":
            # mean pairwise depth gap, in pixels at the members' mean vote depth
            mean_gap = sum(abs(zi - zj) for zi, zj in pairs) / max(len(pairs), 1)
            focal = math.sqrt(K[0][0] * K[1][1])
            distortions.append(mean_gap * focal / max(sum(z) / m, options.vote_near_plane))
        elif options.distortion == "squared":
            distortions.append(sum((zi - zj) ** 2 for zi, zj in pairs))
        else:
            distortions.append(0.0)
    dtype = torch.float64
    return VoteRender(
        mean_vote=torch.tensor(mean_votes, dtype=dtype),
        projected_vote=torch.tensor(projected, dtype=dtype),
        count=torch.tensor(counts, dtype=torch.long),
        distortion=torch.tensor(distortions, dtype=dtype),
    )


def assert_render_close(actual, expected, rtol=1e-9, atol=1e-9):
    assert torch.equal(actual.count.cpu(), expected.count.cpu())
    for name in ("mean_vote", "projected_vote", "distortion"):
        torch.testing.assert_close(
            getattr(actual, name).cpu(), getattr(expected, name).cpu(), rtol=rtol, atol=atol, msg=name
        )


ALL_OPTIONS = [
    VoteRenderOptions(weighting=w, blend_space=b, distortion=d, vote_transmittance=t)
    for w, b, d, t in itertools.product(
        ("uniform", "alpha_t"), ("3d", "2d"), ("l1", "l1_pixels", "squared", "none"), (0.01, 0.0)
    )
]


def option_id(o):
    detach = "" if o.detach_geometry else "-geometry_grads"
    return f"{o.weighting}-{o.blend_space}-{o.distortion}-T{o.vote_transmittance}{detach}"


@pytest.fixture(scope="module")
def small_scene():
    width, height = 24, 20
    return random_scene(60, width, height, seed=1), sample_pixels(width, height, seed=2)


# ---------------------------------------------------------------------------
# Reference against the literal brute force


@pytest.mark.parametrize("options", ALL_OPTIONS, ids=option_id)
def test_reference_matches_brute_force(small_scene, options):
    scene, pixel_xy = small_scene
    expected = brute_force(scene, pixel_xy, options)
    actual = call(render_votes_reference, scene, pixel_xy, options, pixel_chunk=97)
    assert_render_close(actual, expected)
    # the scene exercises the interesting regimes
    assert expected.count.max() >= 3 and (expected.count == 0).any() and (expected.count == 1).any()


def test_scene_hits_both_walk_endings(small_scene):
    """Guard on the fixture: the default threshold, not only the colour stop, ends walks."""
    scene, pixel_xy = small_scene
    cut = brute_force(scene, pixel_xy, VoteRenderOptions(distortion="none"))
    uncut = brute_force(scene, pixel_xy, VoteRenderOptions(distortion="none", vote_transmittance=0.0))
    assert (uncut.count > cut.count).sum() > 20


def test_projection_matches_gsplats_pixel_frame():
    """Votes are projected into the same continuous frame gsplat puts means2d in."""
    width, height = 24, 20
    g = torch.Generator().manual_seed(4)
    means = (torch.rand(30, 3, generator=g, dtype=torch.float64) - 0.5) * 2.0
    viewmat = look_at([0.3, -4.0, 0.5], [0.0, 0.0, 0.0])
    K = torch.tensor([[21.0, 0.0, 11.3], [0.0, 23.0, 9.7], [0.0, 0.0, 1.0]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64).repeat(30, 1)
    scales = torch.full((30, 3), 0.1, dtype=torch.float64)
    means2d, _, _, _ = project_gaussians(means, quats, scales, viewmat, K, width, height)
    torch.testing.assert_close(project_to_pixels(means, viewmat, K), means2d)


def test_votes_behind_camera_stay_finite(small_scene):
    scene, pixel_xy = small_scene
    scene = dict(scene)
    camera_centre = -scene["viewmat"][:3, :3].T @ scene["viewmat"][:3, 3]
    scene["votes"] = camera_centre - 0.5 * (scene["votes"] - camera_centre)  # mirrored behind the camera
    options = VoteRenderOptions()
    actual = call(render_votes_reference, scene, pixel_xy, options)
    assert torch.isfinite(actual.projected_vote).all()
    assert_render_close(actual, brute_force(scene, pixel_xy, options))


# ---------------------------------------------------------------------------
# Gradients


def tiny_case(seed=3):
    width, height = 8, 6
    scene = random_scene(8, width, height, seed=seed)
    scene["opacities"] = 0.2 + 0.6 * torch.rand(8, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return scene, sample_pixels(width, height, seed=seed, extra=4)[::5]


@pytest.mark.parametrize(
    "options",
    [
        VoteRenderOptions(),
        VoteRenderOptions(weighting="alpha_t", blend_space="2d", distortion="squared"),
        VoteRenderOptions(distortion="l1", vote_transmittance=0.0),
    ],
    ids=option_id,
)
def test_reference_gradcheck_votes(options):
    scene, pixel_xy = tiny_case()
    assert call(render_votes_reference, scene, pixel_xy, options).count.max() >= 2

    def fn(votes):
        out = call(render_votes_reference, {**scene, "votes": votes}, pixel_xy, options)
        return out.mean_vote, out.projected_vote, out.distortion

    assert torch.autograd.gradcheck(fn, (scene["votes"].clone().requires_grad_(),))


def test_reference_gradcheck_geometry_when_not_detached():
    scene, pixel_xy = tiny_case()
    options = VoteRenderOptions(weighting="alpha_t", detach_geometry=False)

    def fn(means2d, opacities, votes):
        out = call(
            render_votes_reference,
            {**scene, "means2d": means2d, "opacities": opacities, "votes": votes},
            pixel_xy,
            options,
        )
        return out.mean_vote, out.projected_vote, out.distortion

    inputs = tuple(scene[k].clone().requires_grad_() for k in ("means2d", "opacities", "votes"))
    assert torch.autograd.gradcheck(fn, inputs)
    # and the geometry gradient is not trivially zero
    out = fn(*inputs)
    means2d_grad, opacities_grad = torch.autograd.grad(out[1].sum(), inputs[:2])
    assert means2d_grad.abs().sum() > 0 and opacities_grad.abs().sum() > 0


@pytest.mark.parametrize("render_fn", ["reference", "tiled"])
@pytest.mark.parametrize("weighting", ["uniform", "alpha_t"])
def test_detach_geometry_blocks_geometry_gradients(small_scene, render_fn, weighting):
    scene, pixel_xy = small_scene
    leaves = {k: v.clone().requires_grad_() for k, v in scene.items()}
    options = VoteRenderOptions(weighting=weighting, detach_geometry=True)
    if render_fn == "reference":
        out = call(render_votes_reference, leaves, pixel_xy, options)
    else:
        offsets, ids = tile_lists_everything(scene, 24, 20, 8)
        out = call(render_votes_tiled, leaves, pixel_xy, options, isect_offsets=offsets, flatten_ids=ids, tile_size=8)
    (out.projected_vote.sum() + out.mean_vote.sum() + out.distortion.sum()).backward()
    for name in ("means2d", "conics", "opacities", "depths", "viewmat", "K"):
        grad = leaves[name].grad
        assert grad is None or not grad.any(), name
    assert leaves["votes"].grad is not None and leaves["votes"].grad.abs().sum() > 0


# ---------------------------------------------------------------------------
# Tiled path against the reference


TILED_OPTIONS = [
    VoteRenderOptions(),
    VoteRenderOptions(vote_transmittance=0.0),
    VoteRenderOptions(weighting="alpha_t", blend_space="2d", distortion="squared"),
    VoteRenderOptions(weighting="alpha_t", distortion="l1", vote_transmittance=0.0),
    VoteRenderOptions(blend_space="2d", distortion="none"),
    VoteRenderOptions(weighting="alpha_t", distortion="squared", detach_geometry=False),
    VoteRenderOptions(weighting="alpha_t", distortion="l1", detach_geometry=False, vote_transmittance=0.0),
]


@pytest.fixture(scope="module")
def tiled_scene():
    width, height, tile_size = 40, 32, 8
    scene = random_scene(120, width, height, seed=5)
    pixel_xy = sample_pixels(width, height, seed=6, extra=60)
    lists = {
        "gsplat": tile_lists_gsplat(scene, width, height, tile_size),
        "everything": tile_lists_everything(scene, width, height, tile_size),
    }
    return scene, pixel_xy, tile_size, lists


def grads_of(render_fn, scene, pixel_xy, options, names, **kwargs):
    leaves = {k: v.clone().requires_grad_(k in names) for k, v in scene.items()}
    out = call(render_fn, leaves, pixel_xy, options, **kwargs)
    g = torch.Generator().manual_seed(0)
    # random cotangents so that every output entry matters
    loss = sum(
        (t * torch.randn(t.shape, generator=g, dtype=t.dtype).to(t.device)).sum()
        for t in (out.mean_vote, out.projected_vote, out.distortion)
    )
    grads = torch.autograd.grad(loss, [leaves[k] for k in names], allow_unused=True)
    return out, [torch.zeros_like(leaves[k]) if gr is None else gr for k, gr in zip(names, grads)]


def assert_tiled_matches_reference(scene, pixel_xy, options, names, tile_lists, tile_size, tol=1e-9, **kwargs):
    """render_votes_tiled over ``tile_lists`` (isect_offsets, flatten_ids) gives render_votes_reference's values and
    gradients of ``names`` within ``tol``; returns the reference gradients."""
    offsets, flatten_ids = tile_lists
    expected, expected_grads = grads_of(render_votes_reference, scene, pixel_xy, options, names)
    actual, actual_grads = grads_of(
        render_votes_tiled,
        scene,
        pixel_xy,
        options,
        names,
        isect_offsets=offsets,
        flatten_ids=flatten_ids,
        tile_size=tile_size,
        **kwargs,
    )
    assert_render_close(actual, expected, rtol=tol, atol=tol)
    for name, a, e in zip(names, actual_grads, expected_grads):
        torch.testing.assert_close(a, e, rtol=tol, atol=tol, msg=name)
    return expected_grads


@pytest.mark.parametrize("device", ["cpu", CUDA_PARAM])
@pytest.mark.parametrize("builder", ["gsplat", "everything"])
@pytest.mark.parametrize("options", TILED_OPTIONS, ids=option_id)
def test_tiled_matches_reference(tiled_scene, options, builder, device):
    scene, pixel_xy, tile_size, lists = tiled_scene
    scene = scene_to(scene, device)
    pixel_xy = pixel_xy.to(device)
    offsets, flatten_ids = (t.to(device) for t in lists[builder])
    names = ["votes"] if options.detach_geometry else ["votes", "means2d", "conics", "opacities"]
    run_lengths = torch.diff(torch.cat([offsets.reshape(-1).long(), offsets.new_tensor([len(flatten_ids)]).long()]))
    chunk = 5
    assert run_lengths.max() > 4 * chunk  # the walk must carry its state across chunks
    expected_grads = assert_tiled_matches_reference(
        scene, pixel_xy, options, names, (offsets, flatten_ids), tile_size, chunk=chunk
    )
    assert expected_grads[0].abs().sum() > 0


@pytest.mark.parametrize("device", ["cpu", CUDA_PARAM])
def test_tiled_matches_reference_float32(tiled_scene, device):
    scene, pixel_xy, tile_size, lists = tiled_scene
    scene = scene_to(scene, device, torch.float32)
    pixel_xy = pixel_xy.to(device=device, dtype=torch.float32)
    tile_lists = tuple(t.to(device) for t in lists["gsplat"])
    assert_tiled_matches_reference(
        scene, pixel_xy, VoteRenderOptions(), ["votes"], tile_lists, tile_size, tol=1e-4, chunk=16
    )


def test_tiled_pixels_outside_the_grid_are_empty(tiled_scene):
    scene, _, tile_size, lists = tiled_scene
    offsets, flatten_ids = lists["everything"]
    outside = torch.tensor([[-0.5, 3.0], [40.5, 3.0], [3.0, -1.0], [3.0, 32.0]], dtype=torch.float64)
    out = call(
        render_votes_tiled,
        scene,
        outside,
        VoteRenderOptions(),
        isect_offsets=offsets,
        flatten_ids=flatten_ids,
        tile_size=tile_size,
    )
    assert (out.count == 0).all() and not out.projected_vote.any()


def test_tiled_default_chunk_matches_reference(tiled_scene):
    """chunk=None sizes the steps from the pixel count and the runs; same values and gradients."""
    scene, pixel_xy, tile_size, lists = tiled_scene
    options = VoteRenderOptions(weighting="alpha_t", detach_geometry=False)
    names = ["votes", "means2d", "conics", "opacities"]
    assert_tiled_matches_reference(scene, pixel_xy, options, names, lists["gsplat"], tile_size)


def opaque_wall(n=60, width=24, height=20, seed=12, dtype=torch.float64):
    """Wide, nearly opaque Gaussians covering every pixel several times: every walk ends early."""
    g = torch.Generator().manual_seed(seed)
    means2d = torch.rand(n, 2, generator=g, dtype=dtype) * torch.tensor([width, height], dtype=dtype)
    return dict(
        means2d=means2d,
        conics=torch.tensor([[1 / 200.0, 0.0, 1 / 200.0]], dtype=dtype).repeat(n, 1),
        opacities=0.9 + 0.1 * torch.rand(n, generator=g, dtype=dtype),
        depths=1.0 + torch.rand(n, generator=g, dtype=dtype),
        votes=torch.randn(n, 3, generator=g, dtype=dtype) + torch.tensor([0.0, 0.0, 4.0], dtype=dtype),
        viewmat=torch.eye(4, dtype=dtype),
        K=intrinsics(20.0, width, height, dtype),
    )


@pytest.mark.parametrize("vote_transmittance", [0.01, 0.0])
def test_walk_exit_is_exact(vote_transmittance):
    """Stopping once no open pixel has entries left gives the same sets as walking every run to its end."""
    scene, pixel_xy = opaque_wall(), sample_pixels(24, 20, seed=13)
    offsets, flatten_ids = tile_lists_everything(scene, 24, 20, 8)
    options = VoteRenderOptions(vote_transmittance=vote_transmittance)
    run_start, run_end = vote_render._pixel_runs(pixel_xy, offsets.reshape(-1).long(), 3, 3, 8, len(flatten_ids))
    geometry = vote_render._geometry_table(scene["means2d"], scene["conics"], scene["opacities"], options)
    args = (geometry, pixel_xy, run_start, run_end, flatten_ids, 4, 60, vote_render._vote_threshold(options))
    with HostSyncCounter() as syncs:
        ids, count = vote_render._tiled_members(*args, options.alpha_max)
    ids_to_end, count_to_end = vote_render._tiled_members(*args, options.alpha_max, early_exit=False)
    assert torch.equal(count, count_to_end) and torch.equal(ids, ids_to_end)
    assert ids.shape == (len(pixel_xy), int(count.max())) and count.min() >= 1
    assert syncs.count < 15 // 2  # 15 steps to the end of the runs; the exit came well before
    reference = call(render_votes_reference, scene, pixel_xy, options)
    assert torch.equal(reference.count, count)


# ---------------------------------------------------------------------------
# Mask levels: one walk, one vote per level


LEVELS = 3

LEVEL_OPTIONS = [
    VoteRenderOptions(),
    VoteRenderOptions(vote_transmittance=0.0, distortion="squared"),
    VoteRenderOptions(weighting="alpha_t", blend_space="2d", distortion="l1"),
    VoteRenderOptions(blend_space="2d", distortion="none"),
    VoteRenderOptions(weighting="alpha_t", distortion="squared", detach_geometry=False),
    VoteRenderOptions(distortion="l1", detach_geometry=False, vote_transmittance=0.0),
]


def with_level_votes(scene, levels=LEVELS, seed=11):
    g = torch.Generator().manual_seed(seed)
    votes = scene["votes"][:, None, :] + 0.3 * torch.randn(
        scene["votes"].shape[0], levels, 3, generator=g, dtype=scene["votes"].dtype
    )
    return {**scene, "votes": votes}


def level_cotangents(render, seed=0):
    g = torch.Generator().manual_seed(seed)
    outputs = (render.mean_vote, render.projected_vote, render.distortion)
    return [torch.randn(t.shape, generator=g, dtype=t.dtype) for t in outputs]


@pytest.mark.parametrize("render_fn", ["reference", "tiled"])
@pytest.mark.parametrize("options", LEVEL_OPTIONS, ids=option_id)
def test_levels_equal_separate_calls(tiled_scene, render_fn, options):
    """[N, L, 3] votes give exactly what L calls with [N, 3] votes give, values and gradients."""
    scene, pixel_xy, tile_size, lists = tiled_scene
    scene = with_level_votes(scene)
    if render_fn == "reference":
        fn, kwargs = render_votes_reference, {}
    else:
        offsets, flatten_ids = lists["gsplat"]
        fn, kwargs = render_votes_tiled, dict(isect_offsets=offsets, flatten_ids=flatten_ids, tile_size=tile_size)
    names = ["votes"] if options.detach_geometry else ["votes", "means2d", "conics", "opacities", "viewmat", "K"]

    leaves = {k: v.clone().requires_grad_(k in names) for k, v in scene.items()}
    joint = call(fn, leaves, pixel_xy, options, **kwargs)
    assert joint.mean_vote.shape == (len(pixel_xy), LEVELS, 3)
    assert joint.projected_vote.shape == (len(pixel_xy), LEVELS, 2)
    assert joint.distortion.shape == (len(pixel_xy), LEVELS) and joint.count.shape == (len(pixel_xy),)
    cotangents = level_cotangents(joint)
    loss = sum((t * c).sum() for t, c in zip((joint.mean_vote, joint.projected_vote, joint.distortion), cotangents))
    joint_grads = torch.autograd.grad(loss, [leaves[k] for k in names], allow_unused=True)

    separate_leaves = {k: v.clone().requires_grad_(k in names) for k, v in scene.items()}
    loss = 0.0
    for level in range(LEVELS):
        one = call(fn, {**separate_leaves, "votes": separate_leaves["votes"][:, level]}, pixel_xy, options, **kwargs)
        assert torch.equal(one.count, joint.count)
        assert one.mean_vote.shape == (len(pixel_xy), 3)
        torch.testing.assert_close(one.mean_vote, joint.mean_vote[:, level], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(one.projected_vote, joint.projected_vote[:, level], rtol=1e-12, atol=1e-10)
        torch.testing.assert_close(one.distortion, joint.distortion[:, level], rtol=1e-12, atol=1e-12)
        loss = loss + sum(
            (t * c[:, level]).sum() for t, c in zip((one.mean_vote, one.projected_vote, one.distortion), cotangents)
        )
    separate_grads = torch.autograd.grad(loss, [separate_leaves[k] for k in names], allow_unused=True)
    for name, a, e in zip(names, joint_grads, separate_grads):
        assert (a is None) == (e is None), name
        if a is not None:
            torch.testing.assert_close(a, e, rtol=1e-10, atol=1e-10, msg=name)
    assert joint_grads[0].abs().sum() > 0
    assert joint.count.max() >= 3 and (joint.count == 0).any()


def test_levels_tiled_match_reference(tiled_scene):
    scene, pixel_xy, tile_size, lists = tiled_scene
    scene = with_level_votes(scene)
    options = VoteRenderOptions(weighting="alpha_t", blend_space="2d", detach_geometry=False)
    names = ["votes", "means2d", "opacities"]
    assert_tiled_matches_reference(scene, pixel_xy, options, names, lists["gsplat"], tile_size, chunk=5)


@pytest.mark.parametrize("render_fn", ["reference", "tiled"])
def test_levels_with_nothing_to_vote(small_scene, render_fn):
    """Level-shaped zeros, still in the graph, for an empty pixel set and for pixels outside the lists."""
    scene, _ = small_scene
    scene = with_level_votes(scene, levels=2)
    votes = scene["votes"].clone().requires_grad_()
    offsets, ids = tile_lists_everything(scene, 24, 20, 8)
    outside = torch.tensor([[-3.5, 2.5], [30.5, 2.5]], dtype=torch.float64)
    for pixel_xy in (torch.zeros(0, 2, dtype=torch.float64), outside):
        if render_fn == "reference" and len(pixel_xy):
            continue  # the dense reference has no tile grid to fall outside of
        if render_fn == "reference":
            out = call(render_votes_reference, {**scene, "votes": votes}, pixel_xy, None)
        else:
            out = call(
                render_votes_tiled,
                {**scene, "votes": votes},
                pixel_xy,
                None,
                isect_offsets=offsets,
                flatten_ids=ids,
                tile_size=8,
            )
        p = len(pixel_xy)
        assert out.mean_vote.shape == (p, 2, 3) and out.projected_vote.shape == (p, 2, 2)
        assert out.distortion.shape == (p, 2) and out.count.shape == (p,) and not out.count.any()
        losses = vote_losses(out, torch.zeros(p, 2, 2, dtype=torch.float64), torch.ones(p, 2, dtype=torch.bool))
        for value in losses.values():
            assert value.shape == (2,) and not value.any() and value.requires_grad
        votes.grad = None
        (losses["vote"].sum() + losses["distortion"].sum()).backward()
        assert votes.grad is not None and not votes.grad.any()


# ---------------------------------------------------------------------------
# Host synchronisations (each one stalls the training step until the GPU catches up)


SYNCING_CALLS = {"tolist", "item", "__bool__", "__int__", "__float__", "__index__", "cpu", "numpy"}
DATA_DEPENDENT_SHAPES = {"nonzero", "argwhere", "masked_select", "unique", "unique_consecutive"}


class HostSyncCounter(TorchFunctionMode):
    """Counts the torch calls made from Python that read device values on the host: item(), bool(),
    int(), tolist(), nonzero-like calls, boolean-mask indexing and repeat_interleave without
    output_size (data-dependent shapes). On CUDA each one waits for the GPU to catch up.
    (A TorchDispatchMode would also see autograd's C++ calls, but its first use imports dynamo: ~5 s.)"""

    def __init__(self):
        super().__init__()
        self.what = []

    @property
    def count(self):
        return len(self.what)

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        if name in ("__getitem__", "__setitem__"):
            index = args[1] if isinstance(args[1], tuple) else (args[1],)
            if any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in index):
                self.what.append(f"{name}[bool]")
        elif name == "repeat_interleave" and kwargs.get("output_size") is None:
            self.what.append(name)
        elif name in SYNCING_CALLS or name in DATA_DEPENDENT_SHAPES:
            self.what.append(name)
        return func(*args, **kwargs)


def test_host_syncs_per_training_step(tiled_scene):
    """All levels' vote pass, forward and backward, with a one-step walk (the default width on a GPU):
    two host reads, however many levels."""
    scene, pixel_xy, tile_size, lists = tiled_scene
    offsets, flatten_ids = lists["gsplat"]
    for levels in (1, 4):
        leveled = with_level_votes(scene, levels=levels) if levels > 1 else scene
        votes = leveled["votes"].clone().requires_grad_()
        target = pixel_xy[:, None, :].expand(-1, levels, -1) + 3.0
        valid = torch.ones(len(pixel_xy), levels, dtype=torch.bool)
        if levels == 1:
            target, valid = target[:, 0], valid[:, 0]
        with HostSyncCounter() as syncs:
            out = call(
                render_votes_tiled,
                {**leveled, "votes": votes},
                pixel_xy,
                VoteRenderOptions(),
                isect_offsets=offsets,
                flatten_ids=flatten_ids,
                tile_size=tile_size,
                chunk=10_000,
            )
            losses = vote_losses(out, target, valid)
            (losses["vote"].sum() + losses["distortion"].sum()).backward()
        # the walk's read (table width, with the input checks); loss input checks
        assert syncs.count == 2, syncs.what
        assert votes.grad.abs().sum() > 0


# ---------------------------------------------------------------------------
# The membership rule on hand-made pixels


def stacked_at_pixel(opacities, dtype=torch.float64):
    """Gaussians centred on pixel (0.5, 0.5), ordered front to back, with votes at x = 0, 1, 2, ..."""
    n = len(opacities)
    return dict(
        means2d=torch.full((n, 2), 0.5, dtype=dtype),
        conics=torch.tensor([[1.0, 0.0, 1.0]], dtype=dtype).repeat(n, 1),
        opacities=torch.tensor(opacities, dtype=dtype),
        depths=torch.arange(1, n + 1, dtype=dtype),
        votes=torch.tensor([[float(i), 0.0, 5.0] for i in range(n)], dtype=dtype),
        viewmat=torch.eye(4, dtype=dtype),
        K=intrinsics(10.0, 2, 2, dtype),
    )


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    "opacities, threshold, expected_members",
    [
        ([1.0], 0.01, [0]),  # a lone opaque Gaussian votes (alpha clamped to 0.99)
        ([1.0, 1.0], 0.01, [0]),  # T after the first is 0.01: at the threshold, so it is the last member
        ([0.5, 1.0, 0.5], 0.01, [0, 1]),  # the second brings T to 0.005: member and last; the third is out
        ([0.5, 0.5, 0.5, 0.5], 0.01, [0, 1, 2, 3]),  # T stays above the threshold: everything votes
        ([0.002, 1.0], 0.01, [1]),  # alpha < 1/255 is skipped, not counted
        ([0.9, 1.0, 1.0, 0.5], 0.0, [0, 1]),  # no cut-off: the third would bring T to 1e-5, ending the colour walk
        ([1.0, 0.5, 0.5], 0.0, [0, 1, 2]),  # no cut-off: everything the colour pass composites
        ([0.95, 0.95, 0.95], 0.01, [0, 1]),  # T: 1 -> 0.05 -> 0.0025
    ],
)
def test_membership_rule(opacities, threshold, expected_members, dtype):
    scene = stacked_at_pixel(opacities, dtype)
    pixel = torch.tensor([[0.5, 0.5]], dtype=dtype)
    # the hand-computed transmittances below use a 0.99 clamp
    options = VoteRenderOptions(vote_transmittance=threshold, alpha_max=0.99)
    expected_mean = torch.tensor([sum(expected_members) / len(expected_members), 0.0, 5.0], dtype=dtype)
    offsets = torch.zeros(1, 1, dtype=torch.int32)
    ids = torch.arange(len(opacities), dtype=torch.int32)
    reference = call(render_votes_reference, scene, pixel, options)
    tiled = call(
        render_votes_tiled, scene, pixel, options, isect_offsets=offsets, flatten_ids=ids, tile_size=16, chunk=1
    )
    for out in (reference, tiled):
        assert out.count.tolist() == [len(expected_members)]
        torch.testing.assert_close(out.mean_vote[0], expected_mean)


def test_walk_constants_are_gsplats():
    assert ALPHA_MIN == 1.0 / 255.0 and COLOUR_STOP_T == 1e-4
    assert VoteRenderOptions().alpha_max == 0.999 and VoteRenderOptions().vote_transmittance == 0.01


# ---------------------------------------------------------------------------
# Losses and edge cases


def hand_render(projected, count, distortion):
    projected = torch.tensor(projected, dtype=torch.float64, requires_grad=True)
    return (
        VoteRender(
            mean_vote=torch.zeros(len(count), 3, dtype=torch.float64),
            projected_vote=projected,
            count=torch.tensor(count),
            distortion=torch.tensor(distortion, dtype=torch.float64),
        ),
        projected,
    )


def test_vote_losses_values():
    render, projected = hand_render(
        [[1.0, 2.0], [5.0, 5.0], [0.0, 0.0], [9.0, 9.0]], count=[2, 1, 0, 3], distortion=[0.5, 0.0, 0.0, 7.0]
    )
    target = torch.tensor([[2.0, 4.0], [5.0, 4.0], [3.0, 3.0], [float("nan"), 0.0]], dtype=torch.float64)
    valid = torch.tensor([True, True, True, False])
    losses = vote_losses(render, target, valid)
    assert set(losses) == {"vote", "distortion"}
    # used pixels: 0 and 1 (pixel 2 has count 0, pixel 3 carries no vote)
    assert losses["vote"].item() == pytest.approx((3.0 + 1.0) / 2)
    assert losses["distortion"].item() == pytest.approx(0.25)
    losses["vote"].backward()
    assert projected.grad.tolist() == [[-0.5, -0.5], [0.0, 0.5], [0.0, 0.0], [0.0, 0.0]]
    assert vote_losses(render, target, valid, VoteRenderOptions(distortion="none"))["distortion"].item() == 0.0


def test_vote_losses_per_level():
    """[P, L] renders: one loss per level, over that level's valid pixels with votes."""
    projected = torch.tensor(
        [[[1.0, 2.0], [0.0, 0.0]], [[5.0, 5.0], [1.0, 1.0]], [[0.0, 0.0], [0.0, 0.0]], [[9.0, 9.0], [4.0, 4.0]]],
        dtype=torch.float64,
        requires_grad=True,
    )
    render = VoteRender(
        mean_vote=torch.zeros(4, 2, 3, dtype=torch.float64),
        projected_vote=projected,
        count=torch.tensor([2, 1, 0, 3]),
        distortion=torch.tensor([[0.5, 1.0], [0.0, 2.0], [0.0, 0.0], [7.0, 3.0]], dtype=torch.float64),
    )
    nan = float("nan")
    target = torch.tensor(
        [[[2.0, 4.0], [nan, nan]], [[5.0, 4.0], [1.0, 3.0]], [[3.0, 3.0], [3.0, 3.0]], [[nan, 0.0], [4.0, 5.0]]],
        dtype=torch.float64,
    )
    valid = torch.tensor([[True, False], [True, True], [True, True], [False, True]])
    losses = vote_losses(render, target, valid)
    # level 0 uses pixels 0 and 1, level 1 pixels 1 and 3 (pixel 2 has an empty voting set)
    assert losses["vote"].tolist() == pytest.approx([(3.0 + 1.0) / 2, (2.0 + 1.0) / 2])
    assert losses["distortion"].tolist() == pytest.approx([0.25, 2.5])
    losses["vote"].sum().backward()
    assert projected.grad.tolist() == [
        [[-0.5, -0.5], [0.0, 0.0]],
        [[0.0, 0.5], [0.0, -0.5]],
        [[0.0, 0.0], [0.0, 0.0]],
        [[0.0, 0.0], [0.0, -0.5]],
    ]
    for level in range(2):
        one = vote_losses(
            VoteRender(render.mean_vote[:, level], projected[:, level], render.count, render.distortion[:, level]),
            target[:, level],
            valid[:, level],
        )
        assert one["vote"].shape == () and one["vote"].item() == pytest.approx(losses["vote"][level].item())
        assert one["distortion"].item() == pytest.approx(losses["distortion"][level].item())
    none = vote_losses(render, target, valid, VoteRenderOptions(distortion="none"))["distortion"]
    assert none.shape == (2,) and not none.any()
    with pytest.raises(ValueError, match="target_xy must have shape"):
        vote_losses(render, target[:, 0], valid)
    with pytest.raises(ValueError, match="valid must be a bool tensor of shape"):
        vote_losses(render, target, valid[:, 0])


def assert_zero_connected_losses(losses, leaf):
    for name, value in losses.items():
        assert value.item() == 0.0 and not torch.isnan(value), name
        assert value.requires_grad, name
    (losses["vote"] + losses["distortion"]).backward()
    assert leaf.grad is not None and not leaf.grad.any()


@pytest.mark.parametrize("render_fn", ["reference", "tiled"])
def test_empty_pixel_set(small_scene, render_fn):
    scene, _ = small_scene
    votes = scene["votes"].clone().requires_grad_()
    pixel_xy = torch.zeros(0, 2, dtype=torch.float64)
    if render_fn == "reference":
        out = call(render_votes_reference, {**scene, "votes": votes}, pixel_xy, None)
    else:
        offsets, ids = tile_lists_everything(scene, 24, 20, 8)
        out = call(
            render_votes_tiled,
            {**scene, "votes": votes},
            pixel_xy,
            None,
            isect_offsets=offsets,
            flatten_ids=ids,
            tile_size=8,
        )
    assert out.mean_vote.shape == (0, 3) and out.projected_vote.shape == (0, 2) and out.count.shape == (0,)
    losses = vote_losses(out, torch.zeros(0, 2, dtype=torch.float64), torch.zeros(0, dtype=torch.bool))
    assert_zero_connected_losses(losses, votes)


@pytest.mark.parametrize("render_fn", ["reference", "tiled"])
def test_no_gaussians_in_view(render_fn):
    votes = torch.zeros(0, 3, dtype=torch.float64, requires_grad=True)
    scene = dict(
        means2d=torch.zeros(0, 2, dtype=torch.float64),
        conics=torch.zeros(0, 3, dtype=torch.float64),
        opacities=torch.zeros(0, dtype=torch.float64),
        depths=torch.zeros(0, dtype=torch.float64),
        votes=votes,
        viewmat=torch.eye(4, dtype=torch.float64),
        K=intrinsics(10.0, 4, 4),
    )
    pixel_xy = pixel_centres(4, 4)
    if render_fn == "reference":
        out = call(render_votes_reference, scene, pixel_xy, None)
    else:
        out = call(
            render_votes_tiled,
            scene,
            pixel_xy,
            None,
            isect_offsets=torch.zeros(1, 1, dtype=torch.int32),
            flatten_ids=torch.zeros(0, dtype=torch.int32),
            tile_size=16,
        )
    assert (out.count == 0).all() and out.count.shape == (16,)
    losses = vote_losses(out, pixel_xy.clone(), torch.ones(16, dtype=torch.bool))
    assert_zero_connected_losses(losses, votes)


def test_no_valid_pixel(small_scene):
    scene, pixel_xy = small_scene
    votes = scene["votes"].clone().requires_grad_()
    out = call(render_votes_reference, {**scene, "votes": votes}, pixel_xy, None)
    assert out.count.sum() > 0
    losses = vote_losses(out, torch.full_like(pixel_xy, float("nan")), torch.zeros(len(pixel_xy), dtype=torch.bool))
    assert_zero_connected_losses(losses, votes)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_votes_are_rejected(small_scene, bad):
    scene, pixel_xy = small_scene
    votes = scene["votes"].clone()
    votes[3, 1] = bad
    with pytest.raises(ValueError, match="votes contain NaN or inf"):
        call(render_votes_reference, {**scene, "votes": votes}, pixel_xy, None)
    offsets, ids = tile_lists_everything(scene, 24, 20, 8)
    with pytest.raises(ValueError, match="votes contain NaN or inf"):
        call(
            render_votes_tiled,
            {**scene, "votes": votes},
            pixel_xy,
            None,
            isect_offsets=offsets,
            flatten_ids=ids,
            tile_size=8,
        )


def test_bad_inputs_are_rejected(small_scene):
    scene, pixel_xy = small_scene
    with pytest.raises(ValueError, match="weighting"):
        VoteRenderOptions(weighting="alpha")
    with pytest.raises(ValueError, match="vote_transmittance"):
        VoteRenderOptions(vote_transmittance=1.0)
    with pytest.raises(ValueError, match="means2d must have shape"):
        call(render_votes_reference, {**scene, "means2d": scene["means2d"][:-1]}, pixel_xy, None)
    with pytest.raises(ValueError, match="votes must have shape"):
        call(render_votes_reference, {**scene, "votes": scene["votes"][:, None, :2]}, pixel_xy, None)
    with pytest.raises(ValueError, match="at least one level"):
        call(render_votes_reference, {**scene, "votes": scene["votes"][:, None][:, :0]}, pixel_xy, None)
    offsets, ids = tile_lists_everything(scene, 24, 20, 8)
    with pytest.raises(ValueError, match="flatten_ids must index"):
        call(render_votes_tiled, scene, pixel_xy, None, isect_offsets=offsets, flatten_ids=ids + 60, tile_size=8)
    out = call(render_votes_reference, scene, pixel_xy, None)
    target = torch.zeros_like(pixel_xy)
    target[out.count > 0] = float("nan")
    with pytest.raises(ValueError, match="target_xy contains NaN"):
        vote_losses(out, target, torch.ones(len(pixel_xy), dtype=torch.bool))


# ---------------------------------------------------------------------------
# The method's promise on a toy scene


def fibonacci_sphere(count, centre, radius):
    i = torch.arange(count, dtype=torch.float64) + 0.5
    polar = torch.acos(1 - 2 * i / count)
    azimuth = math.pi * (1 + 5**0.5) * i
    unit = torch.stack(
        [torch.cos(azimuth) * torch.sin(polar), torch.sin(azimuth) * torch.sin(polar), torch.cos(polar)], dim=1
    )
    return torch.tensor(centre, dtype=torch.float64) + radius * unit


def composite_coverage(means2d, conics, opacities, depths, labels, n_labels, pixel_xy):
    """Per-pixel colour-pass weight of each label (gsplat compositing, dense)."""
    order = torch.argsort(depths)
    means2d, conics, opacities, labels = means2d[order], conics[order], opacities[order], labels[order]
    d = means2d[None] - pixel_xy[:, None]
    sigma = 0.5 * (conics[:, 0] * d[..., 0] ** 2 + conics[:, 2] * d[..., 1] ** 2) + conics[:, 1] * d[..., 0] * d[..., 1]
    alpha = (opacities * torch.exp(-sigma.clamp_min(0))).clamp_max(VoteRenderOptions().alpha_max)
    alpha = torch.where((sigma >= 0) & (alpha >= 1 / 255), alpha, torch.zeros_like(alpha))
    t_before = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], 1), 1)
    weight = torch.where(t_before * (1 - alpha) > 1e-4, alpha * t_before, torch.zeros_like(alpha))
    return weight @ torch.nn.functional.one_hot(labels, n_labels).to(weight.dtype)


def test_votes_converge_to_object_centres():
    """Two spheres of small opaque Gaussians; offsets trained on mask-centroid votes from 8 views."""
    torch.manual_seed(0)
    width = height = 48
    centres = torch.tensor([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]], dtype=torch.float64)
    per_object, radius = 40, 0.25
    means = torch.cat([fibonacci_sphere(per_object, c.tolist(), radius) for c in centres])
    labels = torch.arange(2).repeat_interleave(per_object)
    n = means.shape[0]
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64).repeat(n, 1)
    scales = torch.full((n, 3), 0.07, dtype=torch.float64)
    opacities = torch.full((n,), 0.95, dtype=torch.float64)
    K = intrinsics(60.0, width, height)
    pixels = pixel_centres(width, height)

    views = []
    for k, azimuth in enumerate([45, 75, 105, 135, 225, 255, 285, 315]):
        elevation = math.radians(25 if k % 2 else -20)
        a = math.radians(azimuth)
        eye = [
            3.0 * math.cos(a) * math.cos(elevation),
            3.0 * math.sin(a) * math.cos(elevation),
            3.0 * math.sin(elevation),
        ]
        viewmat = look_at(eye, [0.0, 0.0, 0.0])
        means2d, conics, depths, radii = project_gaussians(means, quats, scales, viewmat, K, width, height)
        assert (radii > 0).all()
        coverage = composite_coverage(means2d, conics, opacities, depths, labels, 2, pixels)
        target = torch.full((len(pixels), 2), float("nan"), dtype=torch.float64)
        for obj in range(2):
            mask = coverage[:, obj] > 0.5
            assert mask.sum() > 20
            index = pixels[mask] - 0.5  # integer pixel indices
            centroid = torch.round(index.mean(dim=0)) + 0.5  # paper Eq. 5, then the continuous frame
            target[mask] = centroid
        valid = ~torch.isnan(target[:, 0])
        views.append((means2d, conics, depths, viewmat, pixels[valid], target[valid]))

    offsets = torch.zeros(n, 3, dtype=torch.float64, requires_grad=True)
    optimiser = torch.optim.Adam([offsets], lr=0.02)
    options = VoteRenderOptions()
    for _ in range(75):
        optimiser.zero_grad()
        total = 0.0
        for means2d, conics, depths, viewmat, pixel_xy, target in views:
            votes = means + offsets
            out = render_votes_reference(means2d, conics, opacities, depths, votes, viewmat, K, pixel_xy, options)
            losses = vote_losses(out, target, torch.ones(len(pixel_xy), dtype=torch.bool), options)
            total = total + losses["vote"] + 0.1 * losses["distortion"]
        total.backward()
        optimiser.step()

    votes = (means + offsets).detach()
    for obj in range(2):
        object_votes = votes[labels == obj]
        start = (means[labels == obj] - centres[obj]).norm(dim=1).mean()
        end = (object_votes - centres[obj]).norm(dim=1).mean()
        error = (object_votes.mean(dim=0) - centres[obj]).norm()
        print(f"object {obj}: centre error {error:.4f}, spread {start:.3f} -> {end:.4f}")
        # targets are rounded to whole pixels (paper Eq. 5); one pixel spans 3 / 60 = 0.05 at the objects
        assert error < 0.05
        assert end < start / 5


def test_pixel_distortion_is_scale_free():
    """l1_pixels gives the same value when the whole scene (votes and camera) is scaled; l1 does not."""
    torch.manual_seed(3)
    n = 12
    means2d = torch.rand(n, 2, dtype=torch.float64) * 4 + 2
    conics = torch.tensor([[0.2, 0.0, 0.2]], dtype=torch.float64).repeat(n, 1)
    opacities = torch.full((n,), 0.3, dtype=torch.float64)
    depths = torch.linspace(1.0, 2.0, n, dtype=torch.float64)
    votes = torch.randn(n, 3, dtype=torch.float64) * 0.2 + torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)
    viewmat = torch.eye(4, dtype=torch.float64)
    K = torch.tensor([[20.0, 0.0, 4.0], [0.0, 20.0, 4.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    pixel_xy = torch.tensor([[4.5, 4.5], [3.5, 5.5]], dtype=torch.float64)
    results = {}
    for mode in ("l1", "l1_pixels"):
        options = VoteRenderOptions(distortion=mode, vote_transmittance=0.0)
        for scale in (1.0, 7.0):
            render = render_votes_reference(
                means2d, conics, opacities, depths * scale, votes * scale, viewmat, K, pixel_xy, options
            )
            results[mode, scale] = render.distortion
    assert (results["l1", 1.0] > 0).all()
    torch.testing.assert_close(results["l1", 7.0], 7.0 * results["l1", 1.0])
    torch.testing.assert_close(results["l1_pixels", 7.0], results["l1_pixels", 1.0])
