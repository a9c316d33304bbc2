"""The fused vote losses (votesplat_ns.core.vote_fused.vote_losses_tiled) held to the torch path.

Each case computes ``vote_losses(render_votes_tiled(..., backend="torch"), target, valid)`` (itself
held to the dense reference in test_vote_render.py) and ``vote_losses_tiled`` on the same inputs,
and compares the losses and their gradient with respect to the votes. Where they run: on CUDA,
and on CPU tensors under Triton's interpreter (``TRITON_INTERPRET=1``, slow: small scenes).
"""

from __future__ import annotations

import functools

import pytest
import torch
from op_counter import OpCounter, count_step, launch_names, launches, model_step
from test_vote_render import call, random_scene, sample_pixels, tile_lists_everything, tile_lists_gsplat

from votesplat_ns.core import vote_fused, vote_kernel
from votesplat_ns.core.vote_maps import label_tensor, pixels_and_targets, voting_pixels
from votesplat_ns.core.vote_render import (
    ALPHA_MIN,
    BACKEND_ENV,
    COLOUR_STOP_T,
    VoteRenderOptions,
    render_votes_reference,
    render_votes_tiled,
    vote_losses,
)

DISTORTIONS = ["l1", "l1_pixels", "squared", "none"]


def _skip_reason(device: str):
    if device == "cuda" and not torch.cuda.is_available():
        return "no CUDA device"
    return vote_kernel.unavailable_reason(torch.device(device))


DEVICES = [
    pytest.param(d, marks=pytest.mark.skipif(_skip_reason(d) is not None, reason=f"{d}: {_skip_reason(d)}"))
    for d in ("cpu", "cuda")
]
WIDTH, HEIGHT, TILE = 24, 16, 8


def to_device(scene, device, dtype=None):
    return {k: v.to(device=device, dtype=dtype or v.dtype) for k, v in scene.items()}


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


@pytest.fixture(autouse=True)
def no_backend_env(monkeypatch):
    monkeypatch.delenv(BACKEND_ENV, raising=False)


def small_blocks(monkeypatch, cap=None):
    """Narrow walk blocks and pair tiles, so runs and voting sets span several; ``cap``: scratch slots per pixel
    (rows that would otherwise hold every member: ``vote_kernel.member_slots``)."""
    monkeypatch.setattr(vote_kernel, "BLOCK", 16)
    monkeypatch.setattr(vote_kernel, "PAIR_BLOCK", 4)
    if cap is not None:
        monkeypatch.setattr(vote_kernel, "CAP", cap)
        monkeypatch.setattr(vote_kernel, "MEMBER_SLOT_BYTES", 0)


def targets(pixel_xy, levels, seed=5):
    """Targets near the pixels, invalid (and NaN) at about a fifth of the (pixel, level) entries."""
    g = torch.Generator().manual_seed(seed)
    p = pixel_xy.shape[0]
    target = pixel_xy.cpu()[:, None, :] + 3.0 * torch.randn(p, levels, 2, generator=g, dtype=pixel_xy.dtype)
    valid = torch.rand(p, levels, generator=g) < 0.8
    valid[1, 0] = False  # a pixel with a vote at some levels only
    if levels > 1:
        valid[1, 1:] = True
    target[~valid] = float("nan")
    return target.to(pixel_xy.device), valid.to(pixel_xy.device)


def fused_losses(scene, votes, pixel_xy, target, valid, lists, options):
    """``vote_fused.vote_losses_tiled`` on a test scene and its (isect_offsets, flatten_ids) at tile TILE."""
    offsets, flatten_ids = lists
    return vote_fused.vote_losses_tiled(
        scene["means2d"],
        scene["conics"],
        scene["opacities"],
        votes,
        scene["viewmat"],
        scene["K"],
        pixel_xy,
        target,
        valid,
        offsets,
        flatten_ids,
        TILE,
        options,
    )


def both_paths(scene, votes, pixel_xy, target, valid, lists, options, weights=(1.3, 0.7)):
    """((vote, distortion), d loss / d votes) for the separate torch path and the fused one."""
    offsets, flatten_ids = lists
    results = []
    for fused in (False, True):
        leaf = votes.clone().requires_grad_()
        if fused:
            losses = fused_losses(scene, leaf, pixel_xy, target, valid, lists, options)
        else:
            render = call(
                render_votes_tiled,
                {**scene, "votes": leaf},
                pixel_xy,
                VoteRenderOptions(**{**options.__dict__, "backend": "torch"}),
                isect_offsets=offsets,
                flatten_ids=flatten_ids,
                tile_size=TILE,
            )
            losses = vote_losses(render, target, valid, options, check_inputs=False)
        (weights[0] * losses["vote"].sum() + weights[1] * losses["distortion"].sum()).backward()
        assert leaf.grad is not None
        results.append(((losses["vote"].detach(), losses["distortion"].detach()), leaf.grad))
    return results


# The cases scripts/test.sh runs a second time under Triton's interpreter (TRITON_INTERPRET=1, ``-m interpreter``;
# conftest.py marks them): the kernels' only run without a GPU, and a slow one (seconds per sampled pixel), so
# one or two cases of each test that launches them rather than every parametrization. Kept: every distortion
# mode at least once, one level and several levels (one level: the scalar-loss shapes too), float32 and
# float64, pixels outside the tile grid and empty tiles, voting sets longer than the scratch row (the slow
# exact path, forward and backward) and ones the rows hold whole, ties in depth, nothing used, the sampled
# (training-step) kernels at full and half vote-map scale, the compact vote maps, kept scratch rows, the
# one-Gaussian warm-up scene, the model's fused step and the one-line errors. Left to the main pass: tests
# that launch no kernel (test_member_bound_holds_the_deepest_voting_set, test_model_flag_selects_the_backend).
# On CUDA every case runs; ``TRITON_INTERPRET=1 pytest tests/test_vote_fused.py`` runs them all on CPU.
INTERPRETER_CASES = (
    "test_fused_matches_separate_path[1-none-cpu]",
    "test_fused_matches_separate_path[2-l1-cpu]",
    "test_fused_matches_separate_path[4-squared-cpu]",
    "test_fused_more_members_than_the_scratch_row[4-l1_pixels-cpu]",
    "test_fused_more_members_than_the_scratch_row[None-squared-cpu]",
    "test_fused_ties_in_depth[l1-2-cpu]",
    "test_fused_ties_in_depth[squared-None-cpu]",
    "test_fused_empty_tiles_and_pixels_without_members[cpu]",
    "test_fused_nothing_used[cpu]",
    "test_fused_float32[cpu]",
    "test_use_fused_only_for_its_options",
    "test_fused_errors[cpu]",
    "test_fused_launches_and_host_reads[l1_pixels-cpu]",
    "test_kept_scratch_rows_carry_nothing_into_the_next_call[cpu]",
    "test_warm_up_process_runs_the_training_steps_call[cpu]",
    "test_warm_up_parts_split_the_kernels[forward-cpu]",
    "test_warm_up_parts_split_the_kernels[backward-cpu]",
    "test_model_vote_step_takes_the_fused_losses[cpu]",
    "test_training_step_takes_the_offsets_gradient_at_once[cpu]",
    "test_model_stops_on_diverged_votes_with_the_fused_losses[cpu]",
    "test_sampled_losses_equal_the_lookup_then_fused_losses[1.0-l1_pixels-4-cpu]",
    "test_sampled_losses_equal_the_lookup_then_fused_losses[0.5-squared-None-cpu]",
    "test_sampled_losses_read_the_compact_vote_maps[cpu]",
    "test_sampled_losses_reject_bad_inputs",
)


# DEVICES' CUDA entry (with its skip mark): the entries are pytest.param objects, which never equal "cuda"
CUDA_ONLY = [d for d in DEVICES if d.values == ("cuda",)]
assert len(CUDA_ONLY) == 1


def assert_paths_agree(results, rtol=1e-9, atol=1e-9):
    ((vote, distortion), grad), ((fused_vote, fused_distortion), fused_grad) = results
    assert fused_vote.shape == vote.shape and fused_distortion.shape == distortion.shape
    torch.testing.assert_close(fused_vote.cpu(), vote.cpu(), rtol=rtol, atol=atol)
    torch.testing.assert_close(fused_distortion.cpu(), distortion.cpu(), rtol=rtol, atol=atol)
    torch.testing.assert_close(fused_grad.cpu(), grad.cpu(), rtol=rtol, atol=atol)


def outside_pixels(dtype=torch.float64):
    """Left of, right of and below the tile grid."""
    return torch.tensor([[-1.5, 3.5], [WIDTH + 2.5, 5.5], [4.5, HEIGHT + 0.5]], dtype=dtype)


# ---------------------------------------------------------------------------


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("distortion", DISTORTIONS)
@pytest.mark.parametrize("levels", [1, 2, 4])
def test_fused_matches_separate_path(levels, distortion, device, monkeypatch):
    small_blocks(monkeypatch)
    scene, level_votes, pixel_xy, lists = scene_of_size(50)
    pixel_xy = torch.cat([outside_pixels(), pixel_xy[3::17]])
    scene, pixel_xy = to_device(scene, device), pixel_xy.to(device)
    lists = tuple(t.to(device) for t in lists["gsplat"])
    target, valid = targets(pixel_xy, levels)
    options = VoteRenderOptions(distortion=distortion)
    results = both_paths(scene, level_votes[:, :levels].to(device), pixel_xy, target, valid, lists, options)
    assert_paths_agree(results)
    assert results[0][1].abs().sum() > 0
    if distortion != "none":
        assert (results[0][0][1] > 0).all()
    if levels == 1:
        # [N, 3] votes and [P, 2] targets: scalar losses
        single = both_paths(scene, level_votes[:, 0].to(device), pixel_xy, target[:, 0], valid[:, 0], lists, options)
        assert single[1][0][0].shape == ()
        assert_paths_agree(single)


def test_member_bound_holds_the_deepest_voting_set():
    """A stack of Gaussians at the least alpha that counts (ALPHA_MIN) makes the longest voting set there is: the
    member rows are as long as it, so no walk takes the slow path unless its rows would take too much memory."""
    n = 2600
    alpha_min = torch.tensor(1.0 / 255.0, dtype=torch.float32).double()  # what the kernels compare against
    scene = dict(
        means2d=torch.full((n, 2), 0.5, dtype=torch.float64),
        conics=torch.tensor([[1.0, 0.0, 1.0]], dtype=torch.float64).expand(n, 3).contiguous(),
        opacities=torch.full((n,), float(alpha_min), dtype=torch.float64),
        depths=torch.linspace(1.0, 2.0, n, dtype=torch.float64),
        votes=torch.randn(n, 3, dtype=torch.float64),
        viewmat=torch.eye(4, dtype=torch.float64),
        K=torch.eye(3, dtype=torch.float64),
    )
    pixel = torch.tensor([[0.5, 0.5]], dtype=torch.float64)
    for threshold in (0.01, 0.5, 0.0):
        count = int(call(render_votes_reference, scene, pixel, VoteRenderOptions(vote_transmittance=threshold)).count)
        bound = vote_kernel.member_bound(threshold, ALPHA_MIN, COLOUR_STOP_T)
        assert bound - 3 <= count <= bound
        slots = vote_kernel.member_slots(threshold, ALPHA_MIN, COLOUR_STOP_T, 4096)
        assert slots >= bound and slots % vote_kernel.PAIR_BLOCK == 0
    # rows that would take more than MEMBER_SLOT_BYTES keep vote_kernel.CAP slots
    assert vote_kernel.member_slots(0.01, ALPHA_MIN, COLOUR_STOP_T, 10**6) == vote_kernel.CAP


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("distortion", ["l1", "l1_pixels", "squared"])
@pytest.mark.parametrize("cap", [4, None])
def test_fused_more_members_than_the_scratch_row(cap, distortion, device, monkeypatch):
    """Pixels with more members than CAP take the slow exact path, forward and backward (cap 4); with rows as
    long as a voting set can be (no cap: ``member_slots``) the compacted rows hold them all."""
    small_blocks(monkeypatch, cap=cap)
    scene, level_votes, pixel_xy, lists = scene_of_size(50)
    pixel_xy = pixel_xy[3::17]
    scene, pixel_xy = to_device(scene, device), pixel_xy.to(device)
    lists = tuple(t.to(device) for t in lists["gsplat"])
    count = call(
        render_votes_tiled,
        scene,
        pixel_xy,
        VoteRenderOptions(backend="torch"),
        isect_offsets=lists[0],
        flatten_ids=lists[1],
        tile_size=TILE,
    ).count
    assert (count > 16).any() and ((count > 0) & (count <= 4)).any()
    target, valid = targets(pixel_xy, 2)
    options = VoteRenderOptions(distortion=distortion)
    assert_paths_agree(both_paths(scene, level_votes[:, :2].to(device), pixel_xy, target, valid, lists, options))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("cap", [None, 2])
@pytest.mark.parametrize("distortion", ["l1", "squared"])
def test_fused_ties_in_depth(cap, distortion, device, monkeypatch):
    """Members with the same vote depth: the same losses; gradients equal up to the split of a tie."""
    small_blocks(monkeypatch, cap=cap)
    scene, level_votes, pixel_xy, lists = scene_of_size(50)
    votes = tied_votes(level_votes[:, :2], TIE_GROUPS).to(device)
    scene, pixel_xy = to_device(scene, device), pixel_xy[3::17].to(device)
    lists = tuple(t.to(device) for t in lists["gsplat"])
    target, valid = targets(pixel_xy, 2)
    results = both_paths(scene, votes, pixel_xy, target, valid, lists, VoteRenderOptions(distortion=distortion))
    ((vote, distortion_loss), grad), ((fused_vote, fused_distortion), fused_grad) = results
    torch.testing.assert_close(fused_vote, vote, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(fused_distortion, distortion_loss, rtol=1e-9, atol=1e-9)
    assert_same_up_to_ties(fused_grad.cpu(), grad.cpu(), TIE_GROUPS)


@pytest.mark.parametrize("device", DEVICES)
def test_fused_empty_tiles_and_pixels_without_members(device, monkeypatch):
    small_blocks(monkeypatch)
    scene = random_scene(40, WIDTH, HEIGHT, seed=31)
    keep = scene["means2d"][:, 0] < 6.0  # the right tiles' runs are empty
    scene = {k: (v[keep] if v.ndim and v.shape[0] == 40 else v) for k, v in scene.items()}
    scene["opacities"] = scene["opacities"].clamp_max(0.3)
    lists = tile_lists_gsplat(scene, WIDTH, HEIGHT, TILE)
    ends = torch.cat([lists[0].reshape(-1)[1:].long(), torch.tensor([len(lists[1])])])
    assert (ends == lists[0].reshape(-1).long()).any()
    pixel_xy = torch.tensor(
        [[1.5, 1.5], [3.5, 7.5], [5.5, 12.5], [12.5, 3.5], [20.5, 10.5], [23.5, 15.5], [-2.0, 3.0], [30.0, 3.0]],
        dtype=torch.float64,
    )
    votes = scene["votes"][:, None, :].repeat(1, 2, 1)
    scene, pixel_xy, votes = to_device(scene, device), pixel_xy.to(device), votes.to(device)
    lists = tuple(t.to(device) for t in lists)
    target, valid = targets(pixel_xy, 2)
    for distortion in ("l1_pixels", "squared"):
        results = both_paths(scene, votes, pixel_xy, target, valid, lists, VoteRenderOptions(distortion=distortion))
        assert_paths_agree(results)


@pytest.mark.parametrize("device", DEVICES)
def test_fused_nothing_used(device, monkeypatch):
    """No used pixel (no member anywhere, or no valid target): zero losses, attached, zero gradient."""
    small_blocks(monkeypatch)
    scene, level_votes, pixel_xy, lists = scene_of_size(50)
    scene, pixel_xy = to_device(scene, device), pixel_xy[3::29].to(device)
    lists = tuple(t.to(device) for t in lists["gsplat"])
    target, valid = targets(pixel_xy, 2)
    cases = [
        ({**scene, "opacities": torch.full_like(scene["opacities"], 1e-3)}, valid),  # every alpha < 1/255
        (scene, torch.zeros_like(valid)),
    ]
    for case_scene, case_valid in cases:
        results = both_paths(
            case_scene, level_votes[:, :2].to(device), pixel_xy, target, case_valid, lists, VoteRenderOptions()
        )
        assert_paths_agree(results)
        (vote, distortion), grad = results[1]
        assert not vote.any() and not distortion.any() and not grad.any()


@pytest.mark.parametrize("device", DEVICES)
def test_fused_float32(device, monkeypatch):
    small_blocks(monkeypatch)
    scene, level_votes, pixel_xy, lists = scene_of_size(50)
    scene = to_device(scene, device, torch.float32)
    pixel_xy = pixel_xy[3::17].to(device=device, dtype=torch.float32)
    lists = tuple(t.to(device) for t in lists["gsplat"])
    target, valid = targets(pixel_xy, 2)
    votes = level_votes[:, :2].to(device=device, dtype=torch.float32)
    results = both_paths(scene, votes, pixel_xy, target, valid, lists, VoteRenderOptions(distortion="l1_pixels"))
    assert_paths_agree(results, rtol=1e-4, atol=1e-4)


# ---------------------------------------------------------------------------
# Dispatch and errors


def test_use_fused_only_for_its_options(monkeypatch):
    """Backend "triton" takes the fused losses where the switches allow (the others take the torch path) and
    refuses tensors the kernels cannot take; "auto" takes them on CUDA only, "torch" never;
    VOTESPLAT_VOTE_BACKEND stands for "auto" and must name a backend."""
    votes, pixel_xy = torch.zeros(3, 2, 3), torch.zeros(4, 2)
    runs = vote_kernel.unavailable_reason(votes.device) is None
    triton = VoteRenderOptions(backend="triton", distortion="squared")
    if runs:
        assert vote_fused.use_fused(triton, votes, pixel_xy)
    else:
        with pytest.raises(ValueError, match="backend='triton' cannot run"):
            vote_fused.use_fused(triton, votes, pixel_xy)
    assert not vote_fused.use_fused(VoteRenderOptions(), votes, pixel_xy)  # auto on CPU: the torch path
    assert not vote_fused.use_fused(VoteRenderOptions(backend="torch"), votes, pixel_xy)
    for switch in ({"weighting": "alpha_t"}, {"blend_space": "2d"}, {"detach_geometry": False}):
        assert not vote_fused.use_fused(VoteRenderOptions(backend="triton", **switch), votes, pixel_xy)
    if runs:  # the kernels give pixel_xy no gradient
        with pytest.raises(ValueError, match="pixel_xy"):
            vote_fused.use_fused(triton, votes, pixel_xy.clone().requires_grad_())
        with pytest.raises(ValueError, match="float32 or float64"):
            vote_fused.use_fused(triton, votes.half(), pixel_xy)
    monkeypatch.setenv(BACKEND_ENV, "triton")
    if runs:
        assert vote_fused.use_fused(VoteRenderOptions(), votes, pixel_xy)
    else:
        with pytest.raises(ValueError, match="backend='triton' cannot run"):
            vote_fused.use_fused(VoteRenderOptions(), votes, pixel_xy)
    monkeypatch.setenv(BACKEND_ENV, "fast")
    with pytest.raises(ValueError, match=BACKEND_ENV):
        vote_fused.use_fused(VoteRenderOptions(), votes, pixel_xy)
    with pytest.raises(ValueError, match="backend must be one of"):
        VoteRenderOptions(backend="cuda")


def test_model_flag_selects_the_backend():
    import tyro
    from nerfstudio.engine.trainer import TrainerConfig

    from votesplat_ns.ns.method import votesplat_trainer_config

    config = tyro.cli(
        TrainerConfig, default=votesplat_trainer_config(), args=["--pipeline.model.vote-backend", "torch"]
    )
    assert config.pipeline.model.vote_render_options().backend == "torch"
    assert votesplat_trainer_config().pipeline.model.vote_render_options().backend == "auto"


@pytest.mark.parametrize("device", DEVICES)
def test_fused_errors(device):
    scene, level_votes, pixel_xy, lists = scene_of_size(50)
    scene, pixel_xy = to_device(scene, device), pixel_xy[:4].to(device)
    votes = level_votes[:, :2].to(device)
    offsets, flatten_ids = (t.to(device) for t in lists["gsplat"])
    target, valid = targets(pixel_xy, 2)

    def run(options=None, **changes):
        args = dict(
            means2d=scene["means2d"],
            conics=scene["conics"],
            opacities=scene["opacities"],
            votes=votes,
            viewmat=scene["viewmat"],
            K=scene["K"],
            pixel_xy=pixel_xy,
            target_xy=target,
            valid=valid,
            isect_offsets=offsets,
            flatten_ids=flatten_ids,
            tile_size=TILE,
            options=options,
        )
        return vote_fused.vote_losses_tiled(**{**args, **changes})

    with pytest.raises(ValueError, match="uniform weights"):
        run(VoteRenderOptions(weighting="alpha_t"))
    with pytest.raises(ValueError, match="target_xy must have shape"):
        run(target_xy=target[:, 0])
    with pytest.raises(ValueError, match="valid must be a bool"):
        run(valid=valid.float())
    with pytest.raises(ValueError, match="conics must have shape"):
        run(conics=scene["conics"][:-1])
    with pytest.raises(ValueError, match="share one dtype"):
        run(votes=votes.float())


# ---------------------------------------------------------------------------
# Launches and host reads of a step


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("distortion", ["l1_pixels", "none"])
def test_fused_launches_and_host_reads(distortion, device):
    """Forward + backward of the fused losses, as the model combines them: at most 15 launches (torch
    kernels and Triton kernels), no host read."""
    scene, level_votes, pixel_xy, lists = scene_of_size(50)
    # contiguous, as the model's sampled pixels (a strided slice would cost a copy)
    scene, pixel_xy = to_device(scene, device), pixel_xy[3::29].contiguous().to(device)
    offsets, flatten_ids = (t.to(device) for t in lists["gsplat"])
    target, valid = targets(pixel_xy, 4)
    means = scene["votes"].detach()
    offsets_param = (level_votes.to(device) - means[:, None, :]).requires_grad_()

    def step():
        votes = means[:, None, :] + offsets_param
        options = VoteRenderOptions(distortion=distortion)
        losses = fused_losses(scene, votes, pixel_xy, target, valid, (offsets, flatten_ids), options)
        return losses["vote"].sum() + 0.05 * losses["distortion"].sum()

    step().backward()  # warm-up: first-call caches out of the count
    offsets_param.grad = None
    counter = count_step(step)
    assert counter.total_syncs == 0, dict(counter.syncs)
    # 3 Triton kernels and the zeroed vote gradient; the rest is the test's own loss and its backward
    assert launches(counter) <= 15, launch_names(counter)
    assert counter.triton_launches == 3
    assert offsets_param.grad is not None and offsets_param.grad.abs().sum() > 0


def compiled_variants(kernel) -> int:
    """How many variants Triton has compiled of ``kernel`` (its per-device caches of compiled kernels)."""
    return sum(len(next(part for part in cache if isinstance(part, dict))) for cache in kernel.device_caches.values())


@pytest.mark.parametrize("device", CUDA_ONLY)
def test_fused_kernels_compile_once_for_any_list_length(device):
    """A training step's tile-list length changes every step: after the first step, lengths of every
    remainder mod 16 reuse the compiled kernels (no per-step JIT)."""
    scene, level_votes, pixel_xy, lists = scene_of_size(50)
    scene, pixel_xy = to_device(scene, device), pixel_xy[3::29].contiguous().to(device)
    offsets, flatten_ids = (t.to(device) for t in lists["gsplat"])
    target, valid = targets(pixel_xy, 4)
    votes = level_votes.to(device).requires_grad_()
    kernels = (vote_fused._fused_fwd_kernel, vote_fused._fused_reduce_kernel, vote_fused._fused_bwd_kernel)

    def step(extra):
        # entries past the last tile's run start: the list grows, the kernels' integer arguments change
        ids = torch.cat([flatten_ids, flatten_ids[:extra]])
        losses = fused_losses(scene, votes, pixel_xy, target, valid, (offsets, ids), VoteRenderOptions())
        (losses["vote"].sum() + losses["distortion"].sum()).backward()

    step(0)
    before = [compiled_variants(kernel) for kernel in kernels]
    for extra in range(1, 17):
        step(extra)
    assert [compiled_variants(kernel) for kernel in kernels] == before


def training_like_step(levels: int, distortion: str, device: str) -> None:
    """A training step's vote_losses_sampled, forward and backward, on a 50-Gaussian scene: other sizes, tile
    size and grid than start_warm_up's one-Gaussian scene, the same argument dtypes (float32 votes, gsplat's
    int32 tile lists, int64 draws, the datamanager's int16 labels and int32 voting pixels)."""
    options = VoteRenderOptions(distortion=distortion)
    scene, level_votes, _, lists = scene_of_size(50)
    scene = to_device(scene, device, torch.float32)
    offsets, flatten_ids = (t.to(device=device, dtype=torch.int32) for t in lists["gsplat"])
    votes = level_votes[:, :levels].to(device=device, dtype=torch.float32).requires_grad_()
    labels = torch.randint(1, 3, (levels, HEIGHT * WIDTH), dtype=torch.int16, device=device)
    centroids = torch.rand(levels, 3, 2, device=device) * WIDTH
    voting = torch.arange(HEIGHT * WIDTH, dtype=torch.int32, device=device)
    sample = torch.randint(voting.numel(), (64,), device=device)
    means = torch.zeros(len(votes), 3, device=device)
    args = (scene["means2d"], scene["conics"], scene["opacities"], means, votes, scene["viewmat"], scene["K"], sample)
    support = (
        torch.zeros(len(votes), levels, device=device),
        torch.full((len(votes), levels), -1, dtype=torch.int32, device=device),
        7,
    )
    losses = vote_fused.vote_losses_sampled(
        *args, voting, labels, centroids, WIDTH, 1.0, offsets, flatten_ids, TILE, options, (2.0, 0.5), support
    )
    losses["total"].backward()
    assert votes.grad is not None and votes.grad.abs().sum() > 0


@pytest.mark.parametrize("device", DEVICES)
def test_kept_scratch_rows_carry_nothing_into_the_next_call(device, monkeypatch):
    """The training step's call (accumulate_grad) keeps the walk's scratch rows for the next one: calls on other
    pixels in turn give what each gives with fresh rows."""
    small_blocks(monkeypatch)
    scene, level_votes, _, lists = scene_of_size(50)
    scene = to_device(scene, device, torch.float32)
    isect_offsets, flatten_ids = (t.to(device=device, dtype=torch.int32) for t in lists["gsplat"])
    offsets = level_votes[:, :2].to(device=device, dtype=torch.float32).requires_grad_()
    labels = (torch.arange(2 * HEIGHT * WIDTH, device=device).reshape(2, -1) % 3).to(torch.int32)
    centroids = torch.rand(2, 3, 2, generator=torch.Generator().manual_seed(3)).to(device) * WIDTH
    voting = torch.arange(HEIGHT * WIDTH, device=device)
    means = torch.zeros(len(offsets), 3, device=device)

    def call(seed):
        # a dozen pixels: each call walks every sampled pixel's run (slow under the interpreter)
        sample = torch.randint(voting.numel(), (12,), generator=torch.Generator().manual_seed(seed)).to(device)
        counts = torch.zeros(len(offsets), 2, device=device)
        support = (counts, torch.full_like(counts, -1, dtype=torch.int32), 1)
        offsets.grad = None
        losses = vote_fused.vote_losses_sampled(
            scene["means2d"], scene["conics"], scene["opacities"], means, offsets, scene["viewmat"], scene["K"],
            sample, voting, labels, centroids, WIDTH, 1.0, isect_offsets, flatten_ids, TILE, VoteRenderOptions(),
            (2.0, 0.5), support, accumulate_grad=True,
        )  # fmt: skip
        return losses["vote"], losses["distortion"], counts, offsets.grad

    monkeypatch.setattr(vote_fused, "_KEPT_SCRATCH", {})
    fresh = {}
    for seed in (1, 2):
        vote_fused._KEPT_SCRATCH.clear()
        fresh[seed] = call(seed)
    assert not torch.equal(fresh[1][0], fresh[2][0])
    for seed in (1, 2, 1):
        vote, distortion, counts, grad = call(seed)
        assert torch.equal(vote, fresh[seed][0]) and torch.equal(distortion, fresh[seed][1])
        assert torch.equal(counts, fresh[seed][2])
        torch.testing.assert_close(grad, fresh[seed][3])  # on CUDA the atomic adds land in any order
    assert len(vote_fused._KEPT_SCRATCH) == 1


@pytest.mark.parametrize("device", DEVICES[:1])
def test_warm_up_process_runs_the_training_steps_call(device):
    """start_warm_up's child (``python -m votesplat_ns.core.vote_warm_up``, here on CPU under the interpreter)
    takes what start_warm_up passes and runs the training step's call to the end."""
    warm_up = vote_fused.start_warm_up(2, VoteRenderOptions(distortion="squared"), torch.device(device))
    warm_up.join()
    assert [process.returncode for process in warm_up.processes] == [0]


@pytest.mark.parametrize("device", DEVICES[:1])
@pytest.mark.parametrize("part", ["forward", "backward"])
def test_warm_up_parts_split_the_kernels(part, device, monkeypatch):
    """start_warm_up's two CUDA children: "forward" runs the forward and reduction kernels and leaves the backward
    alone; "backward" runs the backward kernel alone, on a forward whose voting sets are all empty (so it reads
    none of the forward's unwritten outputs, and scatters no gradient)."""
    from votesplat_ns.core import vote_warm_up

    monkeypatch.setattr(vote_kernel, "_launch", vote_kernel._launch)  # the backward part replaces it: restored
    kernels = {"fwd": vote_fused._fused_fwd_kernel, "reduce": vote_fused._fused_reduce_kernel}
    kernels["bwd"] = vote_fused._fused_bwd_kernel
    calls = []

    def recorded(name, run):
        def wrapped(*args, grid, warmup, **kwargs):
            calls.append((name, "compile" if warmup else "run"))
            return run(*args, grid=grid, warmup=warmup, **kwargs)

        return wrapped

    for name, kernel in kernels.items():
        monkeypatch.setattr(kernel, "run", recorded(name, kernel.run))
    backward = vote_fused._FusedVoteLosses.backward
    zero_grads = []

    def recorded_backward(ctx, *grads):
        result = backward(ctx, *grads)
        zero_grads.append(bool((result[0] == 0).all()))
        return result

    monkeypatch.setattr(vote_fused._FusedVoteLosses, "backward", staticmethod(recorded_backward))
    vote_warm_up.warm_up(2, VoteRenderOptions(), torch.device(device), part)
    if part == "forward":
        assert calls == [("fwd", "run"), ("reduce", "run")] and zero_grads == []
    else:
        assert calls == [("bwd", "run")] and zero_grads == [True]


@pytest.mark.parametrize("device", CUDA_ONLY)
@pytest.mark.parametrize("distortion", ["l1_pixels", "none"])
def test_warm_up_fills_tritons_cache_with_what_a_training_step_launches(distortion, device, tmp_path, monkeypatch):
    """start_warm_up's child process compiles the variants of the three fused kernels that a training step
    launches into Triton's on-disk cache, and nothing in this process (whose GIL the compiler would hold): a
    fresh process that runs a training step after it finds them all there (the cache gains no entry)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    levels = 2
    monkeypatch.setenv("TRITON_CACHE_DIR", str(tmp_path))
    kernels = (vote_fused._fused_fwd_kernel, vote_fused._fused_reduce_kernel, vote_fused._fused_bwd_kernel)
    compiled_here = [compiled_variants(kernel) for kernel in kernels]
    vote_fused.start_warm_up(levels, VoteRenderOptions(distortion=distortion), torch.device(device)).join()
    assert [compiled_variants(kernel) for kernel in kernels] == compiled_here
    entries = sorted(path.relative_to(tmp_path) for path in tmp_path.rglob("*"))
    assert {f"{kernel.fn.__name__}.cubin" for kernel in kernels} <= {path.name for path in entries}
    tests = Path(__file__).resolve().parent
    step = f"import sys; sys.path.insert(0, {str(tests)!r}); import test_vote_fused as t; "
    step += f"t.training_like_step({levels}, {distortion!r}, {device!r})"
    done = subprocess.run(
        [sys.executable, "-c", step], check=False, env=dict(os.environ), capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert sorted(path.relative_to(tmp_path) for path in tmp_path.rglob("*")) == entries


@pytest.mark.parametrize("device", DEVICES[:1])  # the model is built on CPU
def test_model_vote_step_takes_the_fused_losses(device, monkeypatch):
    """VoteSplatModel.vote_loss_terms with the Triton backend and the default switches: the fused losses,
    equal to the torch path's, with no host read; other switches keep the torch path."""
    model, step = model_step(levels=2, n=200, width=32, height=24, pixels=24)
    results = {}
    support = model.gauss_params["vote_support"]
    for backend in ("torch", "triton"):
        monkeypatch.setenv(BACKEND_ENV, backend)
        step(seed=0).backward()  # warm-up
        model.record_vote_support()
        with torch.no_grad():
            support.zero_()
        model.vote_step.support_stamps = None  # the warm-up's step counted with this step's stamp
        counter = OpCounter()
        with counter:
            loss = step(seed=0)
            with counter.phase("backward"):
                loss.backward()
        grad = model.gauss_params["vote_offsets"].grad
        assert grad is not None
        model.record_vote_support()  # the fused backward counted it already: nothing added
        results[backend] = (loss.detach(), grad.clone(), counter, support.detach().clone())
    (loss, grad, _, counts), (fused_loss, fused_grad, counter, fused_counts) = results["torch"], results["triton"]
    torch.testing.assert_close(fused_loss, loss, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(fused_grad, grad, rtol=1e-4, atol=1e-6)
    # the support: what the torch path counts (entries with a gradient), and where the fused count has more,
    # members whose summed gradient cancelled to an exact 0 (L1 signs; the fused backward counts members)
    extra = fused_counts != counts
    assert counts.sum() > 0 and (fused_counts[extra] == 1).all() and (counts[extra] == 0).all()
    assert (grad[extra] == 0).all()
    assert grad.abs().sum() > 0
    assert dict(counter.triton_names) == {"_fused_fwd_kernel": 1, "_fused_reduce_kernel": 1, "_fused_bwd_kernel": 1}
    assert counter.total_syncs == 0, dict(counter.syncs)
    # alpha*T weights: the torch path, no Triton kernel
    monkeypatch.setattr(model, "vote_options", VoteRenderOptions(weighting="alpha_t", distortion="l1_pixels"))
    with OpCounter() as counter:
        step().backward()
    assert counter.triton_launches == 0


@pytest.mark.parametrize("device", DEVICES[:1])  # the model is built on CPU
def test_training_step_takes_the_offsets_gradient_at_once(device, monkeypatch):
    """The trainer's path (_vote_losses, then the backward of the loss dict's sum with the colour losses) runs
    the fused backward at once, outside autograd: the offsets' gradient and support counts of the autograd path,
    bitwise, added to a gradient already there (accumulation); a retrofit (a loss dict of the vote loss alone),
    votes that move the means, mixed precision and no grad mode keep autograd."""
    import functools

    monkeypatch.setenv(BACKEND_ENV, "triton")
    model, step = model_step(levels=2, n=200, width=32, height=24, pixels=24)
    offsets, support = model.gauss_params["vote_offsets"], model.gauss_params["vote_support"]
    colour = torch.zeros((), requires_grad=True)  # splatfacto's losses' stand-in

    def trainer_step(through_autograd: bool, grad=None):
        offsets.grad = None if grad is None else grad.clone()
        with torch.no_grad():
            support.zero_()
        model.vote_step.support_stamps = None
        torch.manual_seed(0)
        model._vote_pixel_generator = None
        if through_autograd:
            losses = {"vote": model.vote_loss_terms(step.batch)[0]}
        else:
            losses = model._vote_losses(step.batch)[0]
        assert losses["vote"].requires_grad == through_autograd
        functools.reduce(torch.add, [colour * 1.0, *losses.values()]).backward()
        model.record_vote_support()
        return losses["vote"].detach(), offsets.grad.clone(), support.detach().clone()

    reference, at_once = trainer_step(True), trainer_step(False)
    for expected, got in zip(reference, at_once):
        assert torch.equal(got, expected)
    assert reference[1].abs().sum() > 0 and reference[2].sum() > 0
    earlier = torch.full_like(offsets, 0.25)
    assert torch.equal(trainer_step(False, earlier)[1], reference[1] + earlier)

    assert model._vote_grad_at_once()
    with torch.no_grad():
        assert not model._vote_grad_at_once()
    with torch.autocast("cpu"):
        assert not model._vote_grad_at_once()
    monkeypatch.setattr(model.config, "votes_move_geometry", True)
    assert not model._vote_grad_at_once()
    monkeypatch.setattr(model.config, "votes_move_geometry", False)
    monkeypatch.setattr(model.config, "retrofit_from", "scene.ply")
    assert model.vote_only and not model._vote_grad_at_once()


@pytest.mark.parametrize("device", DEVICES[:1])  # the model is built on CPU
def test_model_stops_on_diverged_votes_with_the_fused_losses(device, monkeypatch):
    """The fused losses read nothing on the host, so a NaN vote gives a NaN loss; the model reads the loss's
    finiteness on every FUSED_FINITE_CHECK_EVERY-th fused vote step and stops with the same one-line error as
    the torch path, whatever the trainer steps are (votes every 4th step from 500 never land on a step ending
    in 99, where a check on the step count once looked: diverged votes then trained on to the end)."""
    from votesplat_ns.ns.model import FUSED_FINITE_CHECK_EVERY

    model, step = model_step(levels=2, n=200, width=32, height=24, pixels=24)
    monkeypatch.setenv(BACKEND_ENV, "triton")
    with torch.no_grad():
        model.gauss_params["vote_offsets"][:5] = float("nan")
    model.vote_step.fused_steps = 10 * FUSED_FINITE_CHECK_EVERY - 2  # the step after is not a checking one
    model.step = 10 * FUSED_FINITE_CHECK_EVERY - 1  # a step count's checking step: no longer what decides
    assert not torch.isfinite(step())  # no host read, a NaN loss
    model.step = 1000  # a vote step of the default schedule (every 4th from 500), as every step here
    with pytest.raises(ValueError, match="vote offsets have diverged"):
        step()
    assert model.vote_step.fused_steps == 10 * FUSED_FINITE_CHECK_EVERY


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize(
    "scale, distortion, cap",
    [(scale, distortion, None) for distortion in ("l1_pixels", "squared", "none") for scale in (1.0, 0.5)]
    + [(1.0, "l1_pixels", 4)],
)
def test_sampled_losses_equal_the_lookup_then_fused_losses(scale, distortion, cap, device, monkeypatch):
    """vote_losses_sampled (pixel and target lookup in the forward kernel, votes = means + offsets formed
    there, the weighted total made by the reduction) gives the values and the offsets' and means' gradients
    of vote_maps.pixels_and_targets followed by vote_losses_tiled on ``means[:, None] + offsets`` and the
    weighted sum in torch, for the same draw: the same float32 operations (bitwise under the interpreter; on
    the H100 the gradients differ by ~1 ulp). Vote maps at 1/scale of the render size, masks without a vote
    included. ``cap`` 4: most voting sets overflow the scratch row, so the backward walks the run again from
    the positions the forward wrote."""
    small_blocks(monkeypatch, cap=cap)
    levels, masks = 2, 6
    scene, level_votes, _, lists = scene_of_size(50)
    scene = to_device(scene, device, torch.float32)
    votes = level_votes[:, :levels].to(device=device, dtype=torch.float32)
    offsets, flatten_ids = (t.to(device) for t in lists["gsplat"])
    g = torch.Generator().manual_seed(31)
    map_width, map_height = int(WIDTH / scale), int(HEIGHT / scale)
    labels = torch.randint(0, masks + 1, (levels, map_height * map_width), generator=g, dtype=torch.int32)
    centroids = torch.rand(levels, masks + 1, 2, generator=g) * torch.tensor([map_width, map_height])
    centroids[:, 0] = float("nan")  # label 0: no mask
    centroids[0, 2] = float("nan")  # a mask without a vote (cut by the border)
    voting = voting_pixels(labels.reshape(levels, map_height, map_width), centroids)
    assert 0 < voting.numel() < labels.shape[1]
    sample = torch.cat([torch.tensor([0, voting.numel() - 1]), torch.randint(voting.numel(), (16,), generator=g)])
    labels, centroids, voting, sample = (t.to(device) for t in (labels, centroids, voting, sample))
    options = VoteRenderOptions(distortion=distortion)
    means = (0.5 * votes[:, 0]).contiguous()
    vote_offsets = votes - means[:, None]
    n = len(votes)
    support = (torch.zeros(n, levels, device=device), torch.full((n, levels), -1, dtype=torch.int32, device=device))
    geometry = (scene["means2d"], scene["conics"], scene["opacities"])
    view = (scene["viewmat"], scene["K"])
    maps = (sample, voting, labels, centroids, map_width, scale)

    def sampled_losses(means_arg, leaf, stamp, check_inputs=True):
        return vote_fused.vote_losses_sampled(
            *geometry,
            means_arg,
            leaf,
            *view,
            *maps,
            offsets,
            flatten_ids,
            TILE,
            options,
            (1.3, 0.7),
            (*support, stamp),
            check_inputs=check_inputs,
        )

    results, totals, mean_grads = [], [], []
    for sampled in (False, True):
        means_leaf, leaf = means.clone().requires_grad_(), vote_offsets.clone().requires_grad_()
        if sampled:
            losses = sampled_losses(means_leaf, leaf, 5)
            total = losses["total"]
            torch.testing.assert_close(losses["terms"].sum(), total.detach())
            assert not losses["terms"].requires_grad and total.shape == ()
        else:
            looked_up = pixels_and_targets(voting[sample], map_width, labels, centroids, scale)
            level_votes = means_leaf[:, None] + leaf
            losses = vote_fused.vote_losses_tiled(
                *geometry, level_votes, *view, *looked_up, offsets, flatten_ids, TILE, options
            )
            total = 1.3 * losses["vote"].sum() + 0.7 * losses["distortion"].sum()
        total.backward()
        assert leaf.grad is not None and means_leaf.grad is not None
        results.append(((losses["vote"].detach(), losses["distortion"].detach()), leaf.grad))
        totals.append(total.detach())
        mean_grads.append(means_leaf.grad)
    if device == "cpu":  # the interpreter: the same operations give the same bits
        assert_paths_agree(results, rtol=0, atol=0)
        torch.testing.assert_close(mean_grads[1], mean_grads[0], rtol=0, atol=0)
    else:  # compiled, the two variants may contract other multiply-adds: vote gradients ~1 ulp apart
        assert_paths_agree(results, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(mean_grads[1], mean_grads[0], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(totals[1], totals[0])
    assert results[1][1].abs().sum() > 0 and (results[1][0][0] > 0).all()
    # the support the backward counted: the entries that got a gradient, once per stamp
    counted = results[1][1].ne(0).any(-1).float()
    # the support the backward counted: per level, the members of the voting sets of the pixels that vote
    # there, once per stamp (the torch path, one pixel at a time: a pixel's members all get its gradient;
    # summed over pixels, the L1 signs can cancel to an exact 0, and such a member still counts)
    members = torch.zeros(n, levels, dtype=torch.bool)
    pixel_xy, target_xy, valid = pixels_and_targets(voting[sample], map_width, labels, centroids, scale)
    torch_options = VoteRenderOptions(**{**options.__dict__, "backend": "torch"})
    for pixel in range(len(sample)):
        leaf = votes.clone().requires_grad_()
        at = slice(pixel, pixel + 1)
        tiles = dict(isect_offsets=offsets, flatten_ids=flatten_ids, tile_size=TILE)
        render = call(render_votes_tiled, {**scene, "votes": leaf}, pixel_xy[at], torch_options, **tiles)
        vote_losses(render, target_xy[at], valid[at], options, check_inputs=False)["vote"].sum().backward()
        assert leaf.grad is not None
        members |= leaf.grad.ne(0).any(-1).cpu()
    counted = members.float().to(device)
    assert counted.sum() > 0 and torch.equal(support[0], counted)
    assert (results[1][1].ne(0).any(-1) <= members.to(device)).all()  # every entry with a gradient is a member
    for stamp, expected in ((5, counted), (6, 2 * counted)):
        leaf = vote_offsets.clone().requires_grad_()
        # stamp 6: a training step's call, without the argument checks: the same results
        losses = sampled_losses(means, leaf, stamp, check_inputs=stamp == 5)
        losses["total"].backward()
        assert torch.equal(support[0], expected), stamp  # step 5 again: nothing new; step 6: each once more
        exact = {"rtol": 0, "atol": 0} if device == "cpu" else {"rtol": 1e-5, "atol": 1e-6}
        torch.testing.assert_close(leaf.grad, results[1][1], **exact)
        torch.testing.assert_close(losses["total"].detach(), totals[1], **exact)


@pytest.mark.parametrize("device", DEVICES)
def test_sampled_losses_read_the_compact_vote_maps(device, monkeypatch):
    """The datamanager's int16 labels and int32 voting pixels (vote_maps.label_tensor, voting_pixels) give the
    losses, the offsets' gradient and the support count that int32 labels and int64 voting pixels give."""
    small_blocks(monkeypatch)
    scene, level_votes, _, lists = scene_of_size(50)
    scene = to_device(scene, device, torch.float32)
    isect_offsets, flatten_ids = (t.to(device=device, dtype=torch.int32) for t in lists["gsplat"])
    g = torch.Generator().manual_seed(8)
    # ids past int8's range, so that a narrower read than int16's would be caught
    labels = torch.randint(0, 300, (2, HEIGHT, WIDTH), generator=g, dtype=torch.int32)
    centroids = torch.rand(2, 300, 2, generator=g) * WIDTH
    centroids[:, 0] = float("nan")
    centroids[1, 200:] = float("nan")  # masks without a vote
    compact = label_tensor(labels.numpy())
    assert compact.dtype == torch.int16 and torch.equal(compact.int(), labels)
    voting = voting_pixels(compact, centroids)
    assert voting.dtype == torch.int32 and torch.equal(voting, voting_pixels(labels, centroids))
    sample = torch.randint(voting.numel(), (16,), generator=g).to(device)
    means = torch.zeros(len(level_votes), 3, device=device)

    def call(flat_labels, voting_pixel_list):
        offsets = level_votes[:, :2].to(device=device, dtype=torch.float32).requires_grad_()
        counts = torch.zeros(len(offsets), 2, device=device)
        losses = vote_fused.vote_losses_sampled(
            scene["means2d"], scene["conics"], scene["opacities"], means, offsets, scene["viewmat"], scene["K"],
            sample, voting_pixel_list.to(device), flat_labels.reshape(2, -1).to(device), centroids.to(device), WIDTH,
            1.0, isect_offsets, flatten_ids, TILE, VoteRenderOptions(), (2.0, 0.5),
            (counts, torch.full_like(counts, -1, dtype=torch.int32), 1),
        )  # fmt: skip
        losses["total"].backward()
        return losses["vote"], losses["distortion"], counts, offsets.grad

    wide = call(labels, voting.long())
    narrow = call(compact, voting)
    assert (wide[0] > 0).all() and wide[2].sum() > 0
    for got, expected in zip(narrow[:3], wide[:3]):
        assert torch.equal(got, expected)
    torch.testing.assert_close(narrow[3], wide[3])  # on CUDA the atomic adds land in any order


def test_sampled_losses_reject_bad_inputs():
    """One-line errors for what the kernel cannot take (checked before any launch)."""
    scene, level_votes, _, lists = scene_of_size(10)
    scene = to_device(scene, "cpu", torch.float32)
    votes = level_votes[:, :2].float()
    labels, centroids = torch.zeros(2, 16, dtype=torch.int32), torch.zeros(2, 3, 2)
    voting, sample = torch.arange(4), torch.zeros(5, dtype=torch.int64)
    args = (scene["means2d"], scene["conics"], scene["opacities"])
    view = (scene["viewmat"], scene["K"])
    tiles = (*lists["gsplat"], TILE, VoteRenderOptions(backend="triton"))
    if vote_kernel.unavailable_reason(votes.device) is not None:
        pytest.skip("the Triton kernels cannot run here")
    for bad, match in [
        (dict(offsets=votes.double()), "float32 offsets"),
        (dict(means=votes[:-1, 0]), "means must be float32"),
        (dict(voting=voting[:0]), "voting is empty"),
        (dict(labels=labels.long()), "flat_labels must be int16 or int32"),
        (dict(labels=labels.to(torch.uint8)), "flat_labels must be int16 or int32"),
        (dict(centroids=centroids[:1]), "centroids must be float32"),
        (dict(sample=sample.int()), "sample must be a 1-D int64"),
        (dict(voting=voting.short()), "voting a 1-D int32 or int64"),
    ]:
        given = {
            **dict(means=votes[:, 0], offsets=votes, sample=sample, voting=voting, labels=labels, centroids=centroids),
            **bad,
        }
        with pytest.raises(ValueError, match=match):
            vote_fused.vote_losses_sampled(
                *args,
                given["means"],
                given["offsets"],
                *view,
                given["sample"],
                given["voting"],
                given["labels"],
                given["centroids"],
                4,
                1.0,
                *tiles,
            )
