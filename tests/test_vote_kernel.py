"""The fused Triton vote kernels (votesplat_ns.core.vote_kernel) held to the torch vote pass.

Each case renders the same inputs through ``render_votes_tiled`` twice, with
``backend="torch"`` (itself held to the dense reference and the brute-force oracle in
test_vote_render.py) and ``backend="triton"``, and compares values and gradients.

Where they run: on CUDA (compiled kernels), and on CPU tensors under Triton's interpreter
(``TRITON_INTERPRET=1 pytest tests/test_vote_kernel.py``, slow: small scenes, few pixels).
Without triton, or on CPU without the interpreter, the kernel tests skip with the reason;
the dispatch tests run everywhere.
"""

from __future__ import annotations

import functools
import itertools

import pytest
import torch
from test_vote_render import (
    call,
    intrinsics,
    opaque_wall,
    option_id,
    random_scene,
    sample_pixels,
    stacked_at_pixel,
    tile_lists_everything,
    tile_lists_gsplat,
)

from votesplat_ns.core import vote_kernel
from votesplat_ns.core.vote_render import BACKEND_ENV, VoteRenderOptions, render_votes_tiled, vote_losses


def _skip_reason(device: str):
    if device == "cuda" and not torch.cuda.is_available():
        return "no CUDA device"
    return vote_kernel.unavailable_reason(torch.device(device))


DEVICES = [
    pytest.param(d, marks=pytest.mark.skipif(_skip_reason(d) is not None, reason=f"{d}: {_skip_reason(d)}"))
    for d in ("cpu", "cuda")
]


@pytest.fixture(autouse=True)
def no_backend_env(monkeypatch):
    monkeypatch.delenv(BACKEND_ENV, raising=False)


def set_block(monkeypatch, width):
    """Walk blocks of ``width`` entries (None: the default). Narrow blocks make the runs span
    several, so the state carried between blocks and the pairs of blocks are tested."""
    if width is not None:
        monkeypatch.setattr(vote_kernel, "BLOCK", width)


# the interpreter runs one program at a time in Python: one narrow width there
DEVICE_BLOCKS = [
    pytest.param(
        device,
        width,
        id=f"{device}-block{width or 'default'}",
        marks=pytest.mark.skipif(_skip_reason(device) is not None, reason=f"{device}: {_skip_reason(device)}"),
    )
    for device, width in (("cpu", 16), ("cuda", 8), ("cuda", None))
]


def with_backend(options, backend):
    return VoteRenderOptions(**{**options.__dict__, "backend": backend})


def render_and_grads(scene, pixel_xy, options, names, lists, tile_size, seed=0):
    offsets, flatten_ids = lists
    leaves = {k: v.clone().requires_grad_(k in names) for k, v in scene.items()}
    out = call(
        render_votes_tiled,
        leaves,
        pixel_xy,
        options,
        isect_offsets=offsets,
        flatten_ids=flatten_ids,
        tile_size=tile_size,
    )
    g = torch.Generator().manual_seed(seed)
    outputs = (out.mean_vote, out.projected_vote, out.distortion)
    # random cotangents so that every output entry matters
    loss = sum((t * torch.randn(t.shape, generator=g, dtype=t.dtype).to(t.device)).sum() for t in outputs)
    grads = torch.autograd.grad(loss, [leaves[k] for k in names], allow_unused=True)
    return out, [torch.zeros_like(leaves[k]) if gr is None else gr for k, gr in zip(names, grads)]


def named(name):
    """assert_close's message: the output's name, then torch's mismatch numbers."""
    return lambda message: f"{name}: {message}"


def assert_same(actual, expected, rtol, atol):
    assert torch.equal(actual.count.cpu(), expected.count.cpu())
    assert actual.count.dtype == torch.long
    for name in ("mean_vote", "projected_vote", "distortion"):
        a, e = getattr(actual, name), getattr(expected, name)
        assert a.shape == e.shape, name
        torch.testing.assert_close(a.cpu(), e.cpu(), rtol=rtol, atol=atol, msg=named(name))


def compare_backends(scene, pixel_xy, options, lists, tile_size, rtol=1e-9, atol=1e-9):
    names = ["votes"] if options.detach_geometry else ["votes", "means2d", "conics", "opacities", "viewmat", "K"]
    expected, expected_grads = render_and_grads(
        scene, pixel_xy, with_backend(options, "torch"), names, lists, tile_size
    )
    actual, actual_grads = render_and_grads(scene, pixel_xy, with_backend(options, "triton"), names, lists, tile_size)
    assert_same(actual, expected, rtol, atol)
    for name, a, e in zip(names, actual_grads, expected_grads):
        torch.testing.assert_close(a.cpu(), e.cpu(), rtol=rtol, atol=atol, msg=named(name))
    return expected, expected_grads


def to_device(scene, device, dtype=None):
    return {k: v.to(device=device, dtype=dtype or v.dtype) for k, v in scene.items()}


# ---------------------------------------------------------------------------
# Every switch, 1 and 4 levels, against the torch path


WIDTH, HEIGHT, TILE = 24, 16, 8


@functools.cache
def scene_of_size(n):
    """n overlapping Gaussians over the 24 x 16 image: every tile's run holds most of them."""
    scene = random_scene(n, WIDTH, HEIGHT, seed=21)
    outside = torch.tensor([[-1.5, 3.5], [WIDTH + 2.5, 5.5], [4.5, HEIGHT + 0.5]], dtype=torch.float64)
    pixel_xy = torch.cat([outside, sample_pixels(WIDTH, HEIGHT, seed=22, extra=12)])
    lists = {
        "gsplat": tile_lists_gsplat(scene, WIDTH, HEIGHT, TILE),
        "everything": tile_lists_everything(scene, WIDTH, HEIGHT, TILE),
    }
    g = torch.Generator().manual_seed(23)
    level_votes = scene["votes"][:, None, :] + 0.3 * torch.randn(n, 4, 3, generator=g, dtype=torch.float64)
    return scene, level_votes, pixel_xy, lists


@pytest.fixture(scope="module")
def kernel_scene():
    return scene_of_size(50)


SWITCHES = [
    VoteRenderOptions(weighting=w, blend_space=b, distortion=d)
    for w, b, d in itertools.product(("uniform", "alpha_t"), ("3d", "2d"), ("l1", "l1_pixels", "squared", "none"))
] + [
    VoteRenderOptions(vote_transmittance=0.0),
    VoteRenderOptions(weighting="alpha_t", distortion="squared", vote_transmittance=0.0),
    VoteRenderOptions(weighting="alpha_t", distortion="l1_pixels", detach_geometry=False),
    VoteRenderOptions(
        weighting="alpha_t", blend_space="2d", distortion="l1", detach_geometry=False, vote_transmittance=0.0
    ),
    VoteRenderOptions(distortion="squared", detach_geometry=False),
]


@pytest.mark.parametrize("device, width", DEVICE_BLOCKS)
@pytest.mark.parametrize("options", SWITCHES, ids=option_id)
def test_kernel_matches_torch(options, device, width, monkeypatch):
    set_block(monkeypatch, width)
    block = width or vote_kernel.BLOCK
    # three blocks' worth of Gaussians (50 at least), so that the longest runs span more than two blocks
    # at every width, the default one included
    scene, level_votes, pixel_xy, lists = scene_of_size(max(50, 3 * block))
    scene = to_device(scene, device)
    # the interpreter is slow: fewer positions there
    pixel_xy = (pixel_xy[::17] if device == "cpu" else pixel_xy).to(device)
    builder = "everything" if options.vote_transmittance == 0.0 else "gsplat"
    lists = tuple(t.to(device) for t in lists[builder])
    run_lengths = torch.diff(torch.cat([lists[0].reshape(-1).long(), lists[0].new_tensor([len(lists[1])]).long()]))
    assert run_lengths.max() > 2 * block  # runs span several blocks
    # one level ([N, 3] votes) and four ([N, 4, 3]): one walk, every level blended over it
    expected, grads = compare_backends(scene, pixel_xy, options, lists, TILE)
    assert expected.count.max() >= 3 and (expected.count == 0).any() and grads[0].abs().sum() > 0
    leveled = {**scene, "votes": level_votes.to(device)}
    expected, _ = compare_backends(leveled, pixel_xy, options, lists, TILE)
    assert expected.mean_vote.shape == (len(pixel_xy), 4, 3)


@pytest.mark.parametrize("device", DEVICES)
def test_kernel_float32(kernel_scene, device):
    scene, level_votes, pixel_xy, lists = kernel_scene
    scene = to_device({**scene, "votes": level_votes}, device, torch.float32)
    pixel_xy = (pixel_xy[::17] if device == "cpu" else pixel_xy).to(device=device, dtype=torch.float32)
    lists = tuple(t.to(device) for t in lists["gsplat"])
    compare_backends(scene, pixel_xy, VoteRenderOptions(distortion="l1_pixels"), lists, TILE, rtol=1e-4, atol=1e-4)
    compare_backends(
        scene,
        pixel_xy,
        VoteRenderOptions(weighting="alpha_t", detach_geometry=False),
        lists,
        TILE,
        rtol=1e-4,
        atol=1e-4,
    )


# ---------------------------------------------------------------------------
# The distortion over the compacted members, and past their capacity


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("distortion", ["l1", "l1_pixels", "squared"])
@pytest.mark.parametrize(
    "cap, pair_block",
    [(128, 4), (4, 4), (None, 4)],
    ids=["compacted-several-pair-tiles", "more-members-than-cap", "rows-of-member-slots"],
)
def test_kernel_distortion_compacted_and_past_cap(device, distortion, cap, pair_block, monkeypatch):
    """The spread and its gradient over the compacted members (their depths computed from their ids), summed over
    several tiles of pairs; and the exact slow path of pixels with more members than the scratch row holds."""
    set_block(monkeypatch, 16)
    if cap is not None:  # rows of cap slots, not as many as a voting set can have (vote_kernel.member_slots)
        monkeypatch.setattr(vote_kernel, "CAP", cap)
        monkeypatch.setattr(vote_kernel, "MEMBER_SLOT_BYTES", 0)
    monkeypatch.setattr(vote_kernel, "PAIR_BLOCK", pair_block)
    scene, level_votes, pixel_xy, lists = scene_of_size(50)
    pixel_xy = pixel_xy[::17].to(device)
    lists = tuple(t.to(device) for t in lists["gsplat"])
    options = VoteRenderOptions(distortion=distortion)
    expected, _ = compare_backends(to_device(scene, device), pixel_xy, options, lists, TILE)
    counts = expected.count
    # pixels on both sides of the capacity, and tiles of pairs across several pair blocks
    assert (counts > 3 * pair_block).any() and (counts <= (cap or 4)).any() and (counts > 1).sum() >= 5
    if cap is not None and cap < 128:
        assert (counts > cap).any()
    leveled = to_device({**scene, "votes": level_votes}, device)
    compare_backends(leveled, pixel_xy, options, lists, TILE)


def tied_votes(votes, groups):
    """Votes [N, L, 3] where each group of Gaussians shares its first member's vote: ties in z."""
    votes = votes.clone()
    for group in groups:
        votes[group[1:]] = votes[group[0]].clone()
    return votes


def assert_same_up_to_ties(actual, expected, groups):
    """Gradients [N, ...] that agree everywhere but within tie groups, where only their sum is defined:
    the torch path's sort splits a tie's subgradient unevenly, the kernels' sign sum evenly."""
    actual, expected = actual.cpu(), expected.cpu()
    tied = torch.zeros(actual.shape[0], dtype=torch.bool)
    for group in groups:
        tied[group] = True
        torch.testing.assert_close(actual[group].sum(0), expected[group].sum(0), rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(actual[~tied], expected[~tied], rtol=1e-9, atol=1e-9)


TIE_GROUPS = [[0, 5, 9, 13], [2, 7], [20, 21, 22]]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("cap", [128, 2])
@pytest.mark.parametrize("distortion", ["l1", "l1_pixels", "squared"])
def test_kernel_distortion_with_ties(device, cap, distortion, monkeypatch):
    """Members whose depths tie: the same spread as the torch path; gradients equal up to the split of a tie."""
    set_block(monkeypatch, 16)
    monkeypatch.setattr(vote_kernel, "CAP", cap)
    monkeypatch.setattr(vote_kernel, "MEMBER_SLOT_BYTES", 0)  # rows of cap slots
    monkeypatch.setattr(vote_kernel, "PAIR_BLOCK", 4)
    scene, level_votes, pixel_xy, lists = scene_of_size(50)
    scene = to_device({**scene, "votes": tied_votes(level_votes, TIE_GROUPS)}, device)
    pixel_xy = pixel_xy[::17].to(device)
    tile_lists = tuple(t.to(device) for t in lists["gsplat"])
    options = VoteRenderOptions(distortion=distortion)
    results = [
        render_and_grads(scene, pixel_xy, with_backend(options, backend), ["votes"], tile_lists, TILE)
        for backend in ("torch", "triton")
    ]
    (expected, (expected_grad,)), (actual, (actual_grad,)) = results
    assert_same(actual, expected, 1e-9, 1e-9)
    assert_same_up_to_ties(actual_grad, expected_grad, TIE_GROUPS)
    assert expected.distortion.abs().sum() > 0


# ---------------------------------------------------------------------------
# Empty tiles, pixels without members, the walk's exit


@pytest.mark.parametrize("device", DEVICES)
def test_kernel_empty_tiles_and_pixels_without_members(device):
    scene = random_scene(40, WIDTH, HEIGHT, seed=31)
    # only the Gaussians of the left half of the image: the right tiles' runs are empty
    keep = scene["means2d"][:, 0] < 6.0
    scene = {k: (v[keep] if v.ndim and v.shape[0] == 40 else v) for k, v in scene.items()}
    scene["opacities"] = scene["opacities"].clamp_max(0.3)
    lists = tile_lists_gsplat(scene, WIDTH, HEIGHT, TILE)
    offsets, _ = lists
    ends = torch.cat([offsets.reshape(-1)[1:].long(), torch.tensor([len(lists[1])])])
    assert (ends == offsets.reshape(-1).long()).any()  # some tile has an empty run
    pixel_xy = torch.tensor(
        [
            [1.5, 1.5],
            [3.5, 7.5],
            [5.5, 12.5],
            [12.5, 3.5],
            [20.5, 10.5],
            [23.5, 15.5],
            [-2.0, 3.0],
            [30.0, 3.0],
            [7.9, 8.1],
            [9.5, 4.5],
        ],
        dtype=torch.float64,
    )
    scene, pixel_xy = to_device(scene, device), pixel_xy.to(device)
    lists = tuple(t.to(device) for t in lists)
    for options in (
        VoteRenderOptions(),
        VoteRenderOptions(weighting="alpha_t", blend_space="2d", distortion="squared", detach_geometry=False),
    ):
        expected, _ = compare_backends(scene, pixel_xy, options, lists, TILE)
        assert (expected.count == 0).sum() >= 4 and expected.count.max() >= 2


@pytest.mark.parametrize("device", DEVICES)
def test_kernel_nothing_votes(device):
    """No pixel has a member: level-shaped zeros that still back-propagate (zero gradient)."""
    scene = random_scene(30, WIDTH, HEIGHT, seed=32)
    scene["opacities"] = torch.full_like(scene["opacities"], 1e-3)  # every alpha < 1/255
    lists = tuple(t.to(device) for t in tile_lists_everything(scene, WIDTH, HEIGHT, TILE))
    scene = to_device(scene, device)
    votes = scene["votes"][:, None, :].repeat(1, 4, 1).clone().requires_grad_()
    pixel_xy = sample_pixels(WIDTH, HEIGHT, seed=33, extra=0)[::37].to(device)
    options = VoteRenderOptions(backend="triton", distortion="l1_pixels")
    out = call(
        render_votes_tiled,
        {**scene, "votes": votes},
        pixel_xy,
        options,
        isect_offsets=lists[0],
        flatten_ids=lists[1],
        tile_size=TILE,
    )
    assert not out.count.any() and not out.projected_vote.any() and not out.distortion.any()
    assert out.mean_vote.shape == (len(pixel_xy), 4, 3)
    losses = vote_losses(
        out,
        torch.zeros(len(pixel_xy), 4, 2, dtype=torch.float64, device=device),
        torch.ones(len(pixel_xy), 4, dtype=torch.bool, device=device),
        options,
    )
    (losses["vote"].sum() + losses["distortion"].sum()).backward()
    assert votes.grad is not None and not votes.grad.any()


@pytest.mark.parametrize("device, width", DEVICE_BLOCKS)
@pytest.mark.parametrize("vote_transmittance", [0.01, 0.0])
def test_kernel_walk_exit_on_opaque_wall(device, width, vote_transmittance, monkeypatch):
    set_block(monkeypatch, width)
    """Nearly opaque layers end every walk long before the runs do; both thresholds."""
    scene, pixel_xy = opaque_wall(), sample_pixels(24, 20, seed=13, extra=4)[::11]
    lists = tuple(t.to(device) for t in tile_lists_everything(scene, 24, 20, 8))
    options = VoteRenderOptions(vote_transmittance=vote_transmittance, weighting="alpha_t", detach_geometry=False)
    expected, _ = compare_backends(to_device(scene, device), pixel_xy.to(device), options, lists, 8)
    assert expected.count.min() >= 1


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    "opacities, threshold, expected_members",
    [
        ([1.0], 0.01, [0]),
        ([1.0, 1.0], 0.01, [0]),  # T after the first is 1 - 0.99: at the threshold
        ([0.5, 1.0, 0.5], 0.01, [0, 1]),
        ([0.002, 1.0], 0.01, [1]),
        ([0.9, 1.0, 1.0, 0.5], 0.0, [0, 1]),  # the third ends the colour walk
        ([0.95, 0.95, 0.95], 0.01, [0, 1]),
    ],
)
def test_kernel_membership_rule(opacities, threshold, expected_members, dtype, device):
    scene = to_device(stacked_at_pixel(opacities, dtype), device)
    pixel = torch.tensor([[0.5, 0.5]], dtype=dtype, device=device)
    options = VoteRenderOptions(vote_transmittance=threshold, alpha_max=0.99, backend="triton")
    offsets = torch.zeros(1, 1, dtype=torch.int32, device=device)
    ids = torch.arange(len(opacities), dtype=torch.int32, device=device)
    out = call(render_votes_tiled, scene, pixel, options, isect_offsets=offsets, flatten_ids=ids, tile_size=16)
    assert out.count.tolist() == [len(expected_members)]
    expected_mean = torch.tensor([sum(expected_members) / len(expected_members), 0.0, 5.0], dtype=dtype)
    torch.testing.assert_close(out.mean_vote[0].cpu(), expected_mean)


# ---------------------------------------------------------------------------
# A training-sized pass (float32, 4 levels, thousands of pixels on the GPU)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize(
    "options",
    [
        VoteRenderOptions(distortion="l1_pixels"),
        VoteRenderOptions(vote_transmittance=0.0, distortion="l1"),
        VoteRenderOptions(weighting="alpha_t", blend_space="2d", distortion="squared", detach_geometry=False),
    ],
    ids=option_id,
)
def test_kernel_training_sized(options, device):
    from votesplat_ns.ns.rasterizer import project_for_votes

    # the interpreter runs a small version of it
    n, width, height, pixels = (20000, 320, 240, 4096) if device == "cuda" else (150, 48, 32, 16)
    g = torch.Generator().manual_seed(0)
    focal = 0.8 * width
    depth = 2.0 + 6.0 * torch.rand(n, generator=g)
    u, v = torch.rand(n, generator=g) * width, torch.rand(n, generator=g) * height
    means = torch.stack([(u - width / 2) / focal * depth, (v - height / 2) / focal * depth, depth], dim=1)
    scales = torch.exp(torch.empty(n, 3).uniform_(-0.7, 2.0, generator=g)) * depth[:, None] / focal
    quats = torch.randn(n, 4, generator=g)
    opacities = 0.05 + 0.95 * torch.rand(n, generator=g)
    votes = means[:, None, :] + 0.1 * torch.randn(n, 4, 3, generator=g)
    flat = torch.randint(0, width * height, (pixels,), generator=g)
    pixel_xy = (torch.stack([flat % width, flat // width], dim=1).float() + 0.5).to(device)
    K, viewmat = intrinsics(focal, width, height, torch.float32).to(device), torch.eye(4, device=device)
    info = project_for_votes(
        means.to(device), quats.to(device), scales.to(device), opacities.to(device), viewmat, K, width, height
    )
    scene = dict(
        means2d=info["means2d"][0],
        conics=info["conics"][0],
        opacities=info["opacities"][0],
        depths=info["depths"][0],
        votes=votes.to(device),
        viewmat=viewmat,
        K=K,
    )
    names = ["votes"] if options.detach_geometry else ["votes", "means2d", "conics", "opacities", "viewmat", "K"]
    renders = {}
    # float32 through both backends, and the torch path in float64 as the reference for the gradients
    for key, backend, dtype in (
        ("torch", "torch", torch.float32),
        ("triton", "triton", torch.float32),
        ("float64", "torch", torch.float64),
    ):
        leaves = {k: v.detach().to(dtype).clone().requires_grad_(k in names) for k, v in scene.items()}
        out = call(
            render_votes_tiled,
            leaves,
            pixel_xy.to(dtype),
            with_backend(options, backend),
            isect_offsets=info["isect_offsets"][0],
            flatten_ids=info["flatten_ids"],
            tile_size=info["tile_size"],
        )
        renders[key] = (out, leaves)
    # float32: torch's expf and Triton's exp may round an alpha or a transmittance that sits within an ulp of
    # a cut-off to opposite sides; such pixels (expected: none, or a handful of 4096) are left out
    agree = renders["torch"][0].count == renders["triton"][0].count
    assert (~agree).sum() <= 4
    agree &= renders["torch"][0].count == renders["float64"][0].count
    assert (~agree).sum() <= 8
    assert renders["torch"][0].count.float().mean() > 3
    grads = {}
    for key, (out, leaves) in renders.items():
        outputs = (out.mean_vote, out.projected_vote, out.distortion)
        g = torch.Generator().manual_seed(1)
        # the same cotangents for the float64 run
        loss = sum(
            (t[agree] * torch.randn(t[agree].shape, generator=g).to(device=device, dtype=t.dtype)).sum()
            for t in outputs
        )
        found = torch.autograd.grad(loss, [leaves[k] for k in names], allow_unused=True)
        grads[key] = [torch.zeros_like(leaves[k]) if gr is None else gr for k, gr in zip(names, found)]
        if key == "triton":
            for name in ("mean_vote", "projected_vote", "distortion"):
                expected = getattr(renders["torch"][0], name)[agree].detach()
                torch.testing.assert_close(
                    getattr(out, name)[agree].detach(), expected, rtol=2e-4, atol=2e-4, msg=named(name)
                )
    # A gradient entry sums thousands of per-pixel terms that partly cancel (up to ~4e3 here, "squared"
    # with 2D blending), accumulated in a different order by each backend, so two float32 results differ
    # by more than any fixed rtol/atol that a wrong gradient would exceed. Each is held to the float64
    # sums instead: Triton's largest error at most 4x the torch path's own, plus a floor of 2e-6 of the
    # largest entry (about 16 float32 ulps of it); a wrong term shows up at the scale of the gradient.
    for name, a, e, exact in zip(names, grads["triton"], grads["torch"], grads["float64"]):
        error = (a.double() - exact).abs().max().item()
        torch_error = (e.double() - exact).abs().max().item()
        scale = exact.abs().max().item()
        assert error <= 4 * torch_error + 2e-6 * scale, (
            f"{name}: Triton's float32 gradient is off the float64 one by {error:.3g}, torch's by "
            f"{torch_error:.3g} (largest entry {scale:.3g})"
        )
    assert grads["torch"][0].abs().sum() > 0


# ---------------------------------------------------------------------------
# Which path runs


def spy_on_kernel(monkeypatch):
    calls = []
    original = vote_kernel.vote_sums

    def spy(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(vote_kernel, "vote_sums", spy)
    return calls


def tiny_tiled_call(options, device="cpu"):
    scene = to_device(stacked_at_pixel([0.5, 0.5]), device)
    pixel = torch.tensor([[0.5, 0.5]], dtype=torch.float64, device=device)
    offsets = torch.zeros(1, 1, dtype=torch.int32, device=device)
    ids = torch.arange(2, dtype=torch.int32, device=device)
    return call(render_votes_tiled, scene, pixel, options, isect_offsets=offsets, flatten_ids=ids, tile_size=16)


def test_auto_backend_on_cpu_is_torch(monkeypatch):
    """The CPU path stays the torch code, even under the interpreter (auto is torch everywhere)."""
    calls = spy_on_kernel(monkeypatch)
    assert tiny_tiled_call(VoteRenderOptions()).count.tolist() == [2]
    assert calls == []


@pytest.mark.parametrize("device", DEVICES)
def test_backend_switches(monkeypatch, device):
    calls = spy_on_kernel(monkeypatch)
    tiny_tiled_call(VoteRenderOptions(backend="triton"), device)
    assert len(calls) == 1
    tiny_tiled_call(VoteRenderOptions(backend="torch"), device)
    assert len(calls) == 1
    monkeypatch.setenv(BACKEND_ENV, "triton")
    tiny_tiled_call(VoteRenderOptions(), device)
    assert len(calls) == 2
    monkeypatch.setenv(BACKEND_ENV, "torch")
    tiny_tiled_call(VoteRenderOptions(), device)
    assert len(calls) == 2
    monkeypatch.delenv(BACKEND_ENV)
    tiny_tiled_call(VoteRenderOptions(), device)  # auto: the torch code on every device (not faster yet)
    assert len(calls) == 2


def test_backend_errors(monkeypatch):
    with pytest.raises(ValueError, match="backend must be one of"):
        VoteRenderOptions(backend="cuda")
    monkeypatch.setenv(BACKEND_ENV, "fast")
    with pytest.raises(ValueError, match=BACKEND_ENV):
        tiny_tiled_call(VoteRenderOptions())
    monkeypatch.delenv(BACKEND_ENV)
    if vote_kernel.unavailable_reason(torch.device("cpu")) is not None:
        with pytest.raises(ValueError, match="backend='triton' cannot run"):
            tiny_tiled_call(VoteRenderOptions(backend="triton"))


@pytest.mark.parametrize("device", DEVICES)
def test_pixel_gradients_stay_on_torch(monkeypatch, device):
    """The kernels give pixel_xy no gradient: "auto" keeps such calls on the torch path, "triton" refuses."""
    monkeypatch.setenv(BACKEND_ENV, "triton")
    calls = spy_on_kernel(monkeypatch)
    scene = to_device(stacked_at_pixel([0.5, 0.5]), device)
    pixel = torch.tensor([[0.7, 0.4]], dtype=torch.float64, device=device, requires_grad=True)
    offsets = torch.zeros(1, 1, dtype=torch.int32, device=device)
    ids = torch.arange(2, dtype=torch.int32, device=device)
    options = VoteRenderOptions(weighting="alpha_t", detach_geometry=False)
    with pytest.raises(ValueError, match="pixel_xy"):
        call(render_votes_tiled, scene, pixel, options, isect_offsets=offsets, flatten_ids=ids, tile_size=16)
    monkeypatch.delenv(BACKEND_ENV)
    out = call(render_votes_tiled, scene, pixel, options, isect_offsets=offsets, flatten_ids=ids, tile_size=16)
    out.mean_vote.sum().backward()
    assert calls == [] and pixel.grad is not None


def test_model_flag_selects_the_backend():
    import tyro
    from nerfstudio.engine.trainer import TrainerConfig

    from votesplat_ns.ns.method import votesplat_trainer_config

    config = tyro.cli(
        TrainerConfig, default=votesplat_trainer_config(), args=["--pipeline.model.vote-backend", "torch"]
    )
    assert config.pipeline.model.vote_render_options().backend == "torch"
    assert votesplat_trainer_config().pipeline.model.vote_render_options().backend == "auto"
