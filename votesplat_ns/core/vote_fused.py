"""The vote step's losses in three Triton launches: ``vote_losses_tiled``.

``vote_losses(render_votes_tiled(...), target_xy, valid)`` for the training defaults (uniform
weights, blending in 3D, ``detach_geometry=True``; any distortion), fused: same values, same
gradient with respect to the votes (the only input that gets one with these options). Same
membership rule, levels and distortions as :mod:`votesplat_ns.core.vote_render` (read its module
docstring); the walk is that of :mod:`votesplat_ns.core.vote_kernel`.

Why: on a GPU the torch path is bound by its launches (the walk, vote table, normalisation, projection,
losses and their backward are each a few torch ops), not by arithmetic. Here everything per pixel happens in
the kernels:

* forward, one program per pixel: the pixel's tile run from ``pixel_xy`` and ``isect_offsets``
  (positions outside the tile grid have an empty run); the walk, summing the members' votes of
  every level and their camera depths (from ``viewmat``); the members' ids to a compacted per-pixel
  scratch row of ``vote_kernel.member_slots`` slots; the mean vote, its projection with ``K``, the L1
  distance to the target where ``valid``, the distortion (over the compacted members, their depths
  computed again from the ids as the walk computed them; pixels with more members than the row holds
  take the exact slow path of ``vote_kernel``'s helpers) and its scaling; per pixel and level it writes the loss
  terms and the gradient of each term with respect to the mean vote and to a member depth.
* a one-program reduction: the per-level means over the used pixels (valid and |M| > 0), in a
  fixed order (no atomics: the losses are deterministic).
* backward, one program per pixel: scatters d loss / d vote to the members (from the compacted
  ids; a pixel past the row's capacity walks its run again).

Launches per step: the two forward kernels, and in the backward a zeroed gradient and one kernel.
No host read: unlike ``render_votes_tiled``, nothing here checks values (finite votes and pixels,
ids and offsets in range); shapes, dtypes and devices are checked. Ids and run positions are
clamped into range, so bad lists give wrong sets, not an out-of-bounds read. The model already
skips ``vote_losses``' own value checks (``check_inputs=False``): targets are finite where valid
by construction.
"""

from __future__ import annotations

import atexit
import dataclasses
import json
import subprocess
import sys
import time
from typing import Dict, List, Optional, Tuple

import torch
from torch import Tensor

from votesplat_ns.core import vote_kernel
from votesplat_ns.core.vote_render import (
    ALPHA_MIN,
    COLOUR_STOP_T,
    VoteRenderOptions,
    _check_shapes,
    _requested_backend,
    _validate_tiles,
    _vote_threshold,
)

# pyright: reportOptionalMemberAccess=false, reportInvalidTypeForm=false
# (as in vote_kernel: ``tl`` is None without triton; ``tl.constexpr`` annotations are Triton's markers.)

triton, tl = vote_kernel.triton, vote_kernel.tl

# Pixels per step of the one-program reduction.
REDUCE_BLOCK = 1024
# how long the first vote step waits for the warm-up process before compiling by itself
WARM_UP_TIMEOUT_S = 300.0
# distortion -> (kernel mode, l1 in pixels)
_DIST = {"none": (0, False), "l1": (1, False), "l1_pixels": (1, True), "squared": (2, False)}
# what vote_losses_sampled reads its vote maps in: the datamanager's compact dtypes (vote_maps.label_tensor,
# voting_pixels) and the wider ones; the kernel widens what it loads
LABEL_DTYPES = (torch.int16, torch.int32)
INDEX_DTYPES = (torch.int32, torch.int64)


def _switches_served(options: VoteRenderOptions) -> bool:
    return options.weighting == "uniform" and options.blend_space == "3d" and options.detach_geometry


def _tensors_unavailable_reason(votes: Tensor, pixel_xy: Tensor) -> Optional[str]:
    """None when the kernels can take these tensors, else why not (one line)."""
    reason = vote_kernel.unavailable_reason(votes.device)
    if reason is None and votes.dtype not in (torch.float32, torch.float64):
        reason = f"the Triton vote kernels take float32 or float64 tensors, got {votes.dtype}"
    if reason is None and pixel_xy.requires_grad:
        reason = "the fused vote losses give pixel_xy no gradient; pass pixel_xy without requires_grad"
    return reason


def fused_unavailable_reason(options: VoteRenderOptions, votes: Tensor, pixel_xy: Tensor) -> Optional[str]:
    """None when ``vote_losses_tiled`` can serve these options and tensors, else why not (one line)."""
    if not _switches_served(options):
        return "the fused vote losses serve uniform weights, blending in 3D and detach_geometry=True only"
    return _tensors_unavailable_reason(votes, pixel_xy)


def use_fused(options: VoteRenderOptions, votes: Tensor, pixel_xy: Tensor) -> bool:
    """Whether a training step should call ``vote_losses_tiled`` rather than the torch path
    (``render_votes_tiled`` + ``vote_losses``): the backend (``VoteRenderOptions.backend`` or
    VOTESPLAT_VOTE_BACKEND) is "triton", or "auto" with CUDA tensors (on an H100 the fused losses take
    1.1-1.7 ms against the torch path's 4.5-7 ms: BENCHMARKS.md, "Fused vote losses"), and the switches are
    the ones it serves (the others take the torch path). Raises where "triton" was asked for and the kernels
    cannot take the tensors."""
    backend = _requested_backend(options)
    if backend == "torch" or (backend == "auto" and votes.device.type != "cuda") or not _switches_served(options):
        return False
    reason = _tensors_unavailable_reason(votes, pixel_xy)
    if backend == "triton" and reason is not None:
        raise ValueError(f"VoteRenderOptions.backend='triton' cannot run: {reason}; use backend='auto' or 'torch'")
    return reason is None


def start_warm_up(levels: int, options: VoteRenderOptions, device: torch.device) -> "KernelWarmUp":
    """Compiles the kernels of ``vote_losses_sampled`` (forward, reduction, backward) for ``levels``
    [N, L, 3] float32 offsets, ``options`` and a support count on CUDA ``device`` into Triton's on-disk cache,
    in child processes (``vote_warm_up``; on CUDA one for the forward's kernels and one for the backward's, which
    compile at once): otherwise the first vote step of a training compiles them on the spot (~5 s on an H100
    host), and a thread of the training process would hold its GIL for as long. Join it before the first real
    call, which then loads them from the cache; a failure here is left to that call, which compiles (and
    reports) by itself."""
    command = [sys.executable, "-m", "votesplat_ns.core.vote_warm_up", str(int(levels))]
    command += [json.dumps(dataclasses.asdict(options)), str(device)]
    # under the interpreter nothing compiles: one child runs the whole call
    parts = ["all"] if vote_kernel.interpreter_enabled() else ["forward", "backward"]
    processes = []
    for part in parts:
        try:
            processes.append(
                subprocess.Popen(
                    command + [part], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
                )
            )
        except OSError:
            break
    return KernelWarmUp(processes)


class KernelWarmUp:
    """The warm-up processes (none when they could not start); stopped when this process exits."""

    def __init__(self, processes: List[subprocess.Popen]):
        self.processes = processes
        if processes:
            atexit.register(self.stop)

    def join(self) -> None:
        """Waits for the warm-up (at most WARM_UP_TIMEOUT_S: past that, the first call compiles by itself)."""
        deadline = time.monotonic() + WARM_UP_TIMEOUT_S
        for process in self.processes:
            try:
                process.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.stop()
                return

    def stop(self) -> None:
        for process in self.processes:
            if process.poll() is None:
                process.kill()  # Triton writes each cache file under a temporary name and renames it
                process.wait()


def vote_losses_tiled(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    votes: Tensor,
    viewmat: Tensor,
    K: Tensor,
    pixel_xy: Tensor,
    target_xy: Tensor,
    valid: Tensor,
    isect_offsets: Tensor,
    flatten_ids: Tensor,
    tile_size: int,
    options: Optional[VoteRenderOptions] = None,
) -> Dict[str, Tensor]:
    """``vote_losses(render_votes_tiled(...), target_xy, valid, options)`` in three launches, no host read.

    Args:
        means2d [N,2], conics [N,3], opacities [N]: the Gaussians projected to one camera (no
            gradient reaches them); entries of Gaussians absent from the lists are never read.
        votes [N,3] or [N,L,3]: world-space votes, differentiable.
        viewmat [4,4], K [3,3]: the camera (no gradient).
        pixel_xy [P,2]: continuous positions (no gradient).
        target_xy [P,2] / [P,L,2], valid [P] / [P,L] bool: as in ``vote_losses``.
        isect_offsets, flatten_ids, tile_size: gsplat's tile lists of this camera, as in
            ``render_votes_tiled``.
        options: must have uniform weights, 3D blending and ``detach_geometry`` (see
            ``fused_unavailable_reason``); ``backend`` is not consulted (the caller chose).

    Returns {"vote", "distortion"}: scalars for [N,3] votes, [L] tensors for [N,L,3], as
    ``vote_losses``. Values are not checked (module docstring).
    """
    options = options or VoteRenderOptions()
    levels, single = _checked_levels(options, votes, pixel_xy)
    if pixel_xy.ndim != 2 or pixel_xy.shape[1] != 2:
        raise ValueError(f"pixel_xy must have shape [P, 2], got {list(pixel_xy.shape)}")
    p = pixel_xy.shape[0]
    level_shape = (p,) if single else (p, levels)
    if tuple(target_xy.shape) != level_shape + (2,):
        raise ValueError(f"target_xy must have shape {list(level_shape + (2,))}, got {list(target_xy.shape)}")
    if tuple(valid.shape) != level_shape or valid.dtype != torch.bool:
        raise ValueError(
            f"valid must be a bool tensor of shape {list(level_shape)}, got {valid.dtype} {list(valid.shape)}"
        )
    if target_xy.device != votes.device or valid.device != votes.device:
        raise ValueError("all inputs of vote_losses_tiled must be on the same device")
    pixels = (
        pixel_xy.detach().contiguous(),
        target_xy.detach().reshape(p, levels, 2).to(votes.dtype).contiguous(),
        valid.reshape(p, levels).contiguous().view(torch.uint8),
    )
    vote, distortion, _total, _weighted = _fused_losses(
        means2d,
        conics,
        opacities,
        (votes, None),
        viewmat,
        K,
        pixels,
        None,
        isect_offsets,
        flatten_ids,
        tile_size,
        options,
        (1.0, 1.0),
        None,
    )
    if single:
        return {"vote": vote[0], "distortion": distortion[0]}
    return {"vote": vote, "distortion": distortion}


def vote_losses_sampled(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    means: Tensor,
    offsets: Tensor,
    viewmat: Tensor,
    K: Tensor,
    sample: Tensor,
    voting: Tensor,
    flat_labels: Tensor,
    centroids: Tensor,
    map_width: int,
    scale: float,
    isect_offsets: Tensor,
    flatten_ids: Tensor,
    tile_size: int,
    options: Optional[VoteRenderOptions] = None,
    weights: Tuple[float, float] = (1.0, 1.0),
    support: Optional[Tuple[Tensor, Tensor, int]] = None,
    check_inputs: bool = True,
    accumulate_grad: bool = False,
) -> Dict[str, Tensor]:
    """``vote_losses_tiled`` at pixels drawn from one view's vote maps, their lookup done in the forward
    kernel, with the votes ``means[:, None] + offsets`` formed in the kernels: the same values and gradients
    as ``vote_losses_tiled(..., means[:, None] + offsets, ..., *vote_maps.pixels_and_targets(voting[sample],
    map_width, flat_labels, centroids, scale), ...)`` without its ~15 launches, and with the weighted sum a
    training step minimises made by the reduction (a step's small torch ops and their backward nodes, not
    the kernels, were most of its cost).

    Args:
        means2d, conics, opacities, viewmat, K, isect_offsets, flatten_ids, tile_size, options: as in
            ``vote_losses_tiled``.
        means [N,3] float32: the Gaussians' world positions (a gradient reaches them only if they require one).
        offsets [N,L,3] float32: the vote offsets, differentiable; the votes are ``means[:, None] + offsets``.
        sample [P] int64: the drawn entries of ``voting`` (in [0, C)).
        voting [C] int32 or int64: flat indices (row * map_width + column) of the view's pixels that carry a
            vote (``vote_maps.voting_pixels``); C >= 1.
        flat_labels [L, H*W] int16 or int32: mask ids per level (``vote_maps.label_tensor``); each dtype is a
            kernel variant of its own; centroids [L, K+1, 2] float32: pixel-index
            centroids, NaN where a mask has no vote (the datamanager's vote maps).
        map_width: W of the vote maps; scale: render resolution over the maps' resolution.
        weights: (w_vote, w_distortion) of "total".
        support: (counts [N,L] float32, stamps [N,L] int32, stamp): the backward also adds 1 to counts[i, l]
            where Gaussian i is a member of the voting set of a pixel that gives level l a gradient (its
            level-l coefficient there is non-zero), once per ``stamp``: it swaps ``stamp`` into stamps[i, l]
            and counts where another value was there. With a new stamp each step, counts[i, l] becomes the
            number of steps in which the offset got a gradient, as ``counts += offsets.grad.ne(0).any(-1)``
            after the step would count without those three launches, except that a member whose gradients
            from several pixels cancel to an exact 0 (L1 signs) counts here.
        check_inputs: False skips the checks of the arguments' shapes, dtypes and devices (and whether the
            kernels can run: ``use_fused``), for a caller that builds them the same way every step (a training
            step: the checks are a fair part of its host time); wrong arguments then fail in the kernels.
        accumulate_grad: True runs the backward of "total" at once, outside autograd, and adds its gradient to
            ``offsets.grad`` (set when None); the returned losses then carry no gradient. For a training step
            whose other losses' backward the trainer runs anyway: the autograd node, its saved tensors and the
            engine's call of a Python backward cost the step host time. ``offsets`` must be a leaf and
            ``means`` must not require a gradient (it would get none).

    Returns {"vote", "distortion"}: [L] tensors as ``vote_losses_tiled``'s; "total": the differentiable scalar
    w_vote * vote.sum() + w_distortion * distortion.sum(); "terms": [2] its two terms, without a gradient (for
    logging: reading them costs no launch). Values are not checked; indices are clamped into range.
    """
    options = options or VoteRenderOptions()
    if check_inputs:
        _check_sampled_inputs(options, means, offsets, sample, voting, flat_labels, centroids, support)
    if accumulate_grad and (means.requires_grad or not offsets.is_leaf):
        raise ValueError(
            "accumulate_grad gives the offsets (a leaf) their gradient and the means none: detach the means"
        )
    p = sample.shape[0]
    # filled by the forward kernel with the drawn pixels' positions (its backward reads them)
    pixel_xy = torch.empty(p, 2, dtype=offsets.dtype, device=offsets.device)
    sampling = (sample.contiguous(), voting.contiguous(), flat_labels.contiguous(), centroids.contiguous())
    geometry = (int(flat_labels.shape[1]), int(map_width), int(centroids.shape[1]), float(scale))
    vote, distortion, total, terms = _fused_losses(
        means2d,
        conics,
        opacities,
        (offsets, means),
        viewmat,
        K,
        (pixel_xy, pixel_xy, sample),  # target and valid are computed in the kernel: placeholders
        (sampling, geometry),
        isect_offsets,
        flatten_ids,
        tile_size,
        options,
        (float(weights[0]), float(weights[1])),
        support,
        check_inputs,
        offsets if accumulate_grad else None,
    )
    return {"vote": vote, "distortion": distortion, "total": total, "terms": terms}


def _check_sampled_inputs(
    options: VoteRenderOptions,
    means: Tensor,
    offsets: Tensor,
    sample: Tensor,
    voting: Tensor,
    flat_labels: Tensor,
    centroids: Tensor,
    support: Optional[Tuple[Tensor, Tensor, int]],
) -> None:
    """``vote_losses_sampled``'s own argument checks (one line each)."""
    levels, single = _checked_levels(options, offsets, sample)
    if single or offsets.dtype != torch.float32:
        raise ValueError(
            f"vote_losses_sampled takes float32 offsets [N, L, 3], got {offsets.dtype} {list(offsets.shape)}"
        )
    if tuple(means.shape) != (offsets.shape[0], 3) or means.dtype != torch.float32:
        raise ValueError(
            f"means must be float32 [{offsets.shape[0]}, 3] (one per offset row), got {means.dtype} {list(means.shape)}"
        )
    if sample.ndim != 1 or voting.ndim != 1 or sample.dtype != torch.int64 or voting.dtype not in INDEX_DTYPES:
        raise ValueError("sample must be a 1-D int64 tensor and voting a 1-D int32 or int64 tensor")
    if voting.numel() == 0:
        raise ValueError("voting is empty: a view without voting pixels has no vote losses to sample")
    if flat_labels.ndim != 2 or flat_labels.shape[0] != levels or flat_labels.dtype not in LABEL_DTYPES:
        raise ValueError(
            f"flat_labels must be int16 or int32 [{levels}, H*W], got {flat_labels.dtype} {list(flat_labels.shape)}"
        )
    if (
        centroids.ndim != 3
        or centroids.shape[0] != levels
        or centroids.shape[2] != 2
        or centroids.dtype != torch.float32
    ):
        raise ValueError(f"centroids must be float32 [{levels}, K+1, 2], got {centroids.dtype} {list(centroids.shape)}")
    if len({t.device for t in (means, offsets, sample, voting, flat_labels, centroids)}) != 1:
        raise ValueError("all inputs of vote_losses_sampled must be on the same device")
    if support is not None:
        counts, stamps, _stamp = support
        level_shape = tuple(offsets.shape[:2])
        if tuple(counts.shape) != level_shape or counts.dtype != torch.float32 or not counts.is_contiguous():
            raise ValueError(f"support counts must be contiguous float32 {list(level_shape)}")
        if tuple(stamps.shape) != level_shape or stamps.dtype != torch.int32 or not stamps.is_contiguous():
            raise ValueError(f"support stamps must be contiguous int32 {list(level_shape)}")
        if counts.device != offsets.device or stamps.device != offsets.device:
            raise ValueError("support counts and stamps must be on the offsets' device")


def _checked_levels(options: VoteRenderOptions, votes: Tensor, pixels: Tensor) -> Tuple[int, bool]:
    """(levels, whether votes are [N,3]) after the checks both entry points share."""
    reason = fused_unavailable_reason(options, votes, pixels)
    if reason is not None:
        raise ValueError(f"the fused vote losses cannot run: {reason}; use render_votes_tiled and vote_losses")
    if votes.ndim not in (2, 3) or votes.shape[-1] != 3 or (votes.ndim == 3 and votes.shape[1] < 1):
        raise ValueError(f"votes must have shape [N, 3] or [N, L, 3] (one vote per level), got {list(votes.shape)}")
    single = votes.ndim == 2
    return (1 if single else votes.shape[1]), single


def _fused_losses(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    votes_and_means: Tuple[Tensor, Optional[Tensor]],
    viewmat: Tensor,
    K: Tensor,
    pixels: Tuple[Tensor, Tensor, Tensor],
    sampled: Optional[Tuple[Tuple[Tensor, ...], Tuple[int, int, int, float]]],
    isect_offsets: Tensor,
    flatten_ids: Tensor,
    tile_size: int,
    options: VoteRenderOptions,
    weights: Tuple[float, float],
    support: Optional[Tuple[Tensor, Tensor, int]],
    check_inputs: bool = True,
    grad_leaf: Optional[Tensor] = None,
) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """[L] vote and distortion losses, the weighted total and its [2] terms; ``votes_and_means`` = (votes,
    None), or (offsets, means) for the votes means[:, None] + offsets; ``pixels`` = (pixel_xy, target, valid)
    as the kernel reads them (or, when ``sampled``, the position buffer the kernel fills). ``grad_leaf``: the
    votes' tensor, to which the gradient of the total is added at once (no autograd; ``vote_losses_sampled``'s
    ``accumulate_grad``)."""
    votes, means = votes_and_means
    n = votes.shape[0]
    levels = 1 if votes.ndim == 2 else votes.shape[1]
    pixel_xy = pixels[0]
    p = pixel_xy.shape[0]
    if check_inputs:
        shapes = {"means2d": (means2d, (n, 2)), "conics": (conics, (n, 3)), "opacities": (opacities, (n,))}
        _check_shapes(n, {**shapes, "viewmat": (viewmat, (4, 4)), "K": (K, (3, 3))})
        floats = (means2d, conics, opacities, votes, viewmat, K, pixel_xy)
        if len({t.dtype for t in floats}) != 1:
            raise ValueError("means2d, conics, opacities, votes, viewmat, K and pixel_xy must share one dtype")
        if len({t.device for t in floats}) != 1:
            raise ValueError("all inputs of the fused vote losses must be on the same device")
        offsets, tiles_high, tiles_wide = _validate_tiles(isect_offsets, flatten_ids, tile_size, None, votes.device)
    else:
        offsets, (tiles_high, tiles_wide) = isect_offsets.reshape(-1), isect_offsets.shape[-2:]

    dist, in_pixels = _DIST[options.distortion]
    if n == 0 or p == 0:
        # nothing to walk: zero losses that stay attached to the graph (zero gradient)
        zero = votes.new_zeros(levels) + votes.sum() * 0.0
        return zero, zero.clone(), zero.sum(), votes.new_zeros(2)
    threshold = _vote_threshold(options)
    consts = vote_kernel._constants(
        (
            threshold,
            options.alpha_max,
            max(threshold, COLOUR_STOP_T),
            ALPHA_MIN,
            COLOUR_STOP_T,
            float(options.vote_near_plane),
        ),
        votes.dtype,
        votes.device,
    )
    # the sampling inputs, or placeholders (never read) and zeros when the pixels are given
    sampling, map_geometry = sampled if sampled is not None else ((offsets,) * 4, (1, 1, 1, 1.0))
    config = (levels, dist, in_pixels, tiles_wide, tiles_high, int(tile_size), flatten_ids.numel(), map_geometry)
    slots = vote_kernel.member_slots(options.vote_transmittance, ALPHA_MIN, COLOUR_STOP_T, p)
    votes = votes.reshape(n, levels, 3).contiguous()
    inputs = (
        votes,
        votes if means is None else means.contiguous(),  # unread placeholder without means
        means2d.detach().contiguous(),
        conics.detach().contiguous(),
        opacities.detach().contiguous(),
        viewmat.detach().contiguous(),
        K.detach().contiguous(),
        *pixels,
        *sampling,
        offsets.contiguous(),
        flatten_ids.contiguous(),
        consts,
        (config, slots, sampled is not None, means is not None, weights, support),
    )
    if grad_leaf is None:
        return _FusedVoteLosses.apply(*inputs)
    with torch.no_grad():
        outputs, saved = _fused_forward(*inputs, keep_scratch=True)
        # d total / d total = 1, read by the kernel from the device (a constant put there once)
        one = vote_kernel._constants((1.0,), votes.dtype, votes.device)
        g_votes, _ = _fused_backward(saved, inputs[-1], (None, None, one), False)
        if grad_leaf.grad is None:
            grad_leaf.grad = g_votes.reshape(grad_leaf.shape)
        else:  # gradients accumulated over steps (the trainer clears them only every few steps)
            grad_leaf.grad.add_(g_votes.reshape(grad_leaf.shape))
    return outputs


# The walk's scratch rows of the last call that ran its backward at once (``accumulate_grad``), kept for the next
# such call of the same shapes: that backward ran in the same call, and the next call's kernels come after it on
# the stream, so nothing reads the rows once they are written again. Three allocations less in a training step.
_KEPT_SCRATCH: Dict[Tuple, Tuple[Tensor, Tensor, Tensor]] = {}


def _walk_scratch(
    p: int, cap: int, levels: int, dtype: torch.dtype, device: torch.device, keep: bool
) -> Tuple[Tensor, Tensor, Tensor]:
    """(walk, members, terms): the forward's scratch rows, kept from the last call with ``keep``."""
    key = (p, cap, levels, dtype, device, torch.cuda.current_stream(device) if device.type == "cuda" else None)
    if keep and key in _KEPT_SCRATCH:
        return _KEPT_SCRATCH[key]
    walk = torch.empty(3, p, dtype=torch.int64, device=device)  # |M|, run start, last member's position
    members = torch.empty(p, cap, dtype=torch.int32, device=device)
    # per pixel and level: loss terms (vote L1, distortion, used) and the backward's coefficients
    # (d vote-L1 / d member vote [3], d distortion / d member depth factor, mean member depth)
    terms = torch.empty(p, 8, levels, dtype=dtype, device=device)
    if keep:
        _KEPT_SCRATCH.clear()  # one shape at a time: a training run keeps its pixel count
        _KEPT_SCRATCH[key] = (walk, members, terms)
    return walk, members, terms


def _fused_forward(
    *inputs, keep_scratch: bool = False
) -> Tuple[Tuple[Tensor, Tensor, Tensor, Tensor], Tuple[Tensor, ...]]:
    """The forward and reduction launches on ``_FusedVoteLosses``' inputs: ((vote, distortion, total, weighted),
    what the backward reads). ``keep_scratch``: the backward runs before the next call (``_walk_scratch``)."""
    votes, means, means2d, conics, opacities, viewmat, K, pixel_xy, target, valid = inputs[:10]
    sample, voting, labels, centroids, offsets, ids, consts, modes = inputs[10:]
    # votes: [N, L, 3] votes, or offsets when split (the votes are means[:, None] + votes)
    config, cap, sampled, split, (w_vote, w_dist), _support = modes
    levels, dist, in_pixels, tiles_wide, tiles_high, tile_size, n_isects, map_geometry = config
    map_pixels, map_width, cent_rows, pix_scale = map_geometry
    p, device, dtype = pixel_xy.shape[0], votes.device, votes.dtype
    walk, members, terms = _walk_scratch(p, cap, levels, dtype, device, keep_scratch)
    vote = torch.empty(levels, dtype=dtype, device=device)
    distortion = torch.empty(levels, dtype=dtype, device=device)
    denominator = torch.empty(levels, dtype=dtype, device=device)
    total = torch.empty((), dtype=dtype, device=device)
    weighted = torch.empty(2, dtype=dtype, device=device)
    lp = vote_kernel._pow2(levels)
    # the leading arguments of both walking kernels (the backward's come from the saved tensors)
    scene = (means2d, conics, opacities, votes, means, viewmat)
    with vote_kernel._on(device):
        vote_kernel._launch(
            _fused_fwd_kernel,
            (p,),
            *scene,
            K,
            pixel_xy,
            target,
            valid,
            sample,
            voting,
            labels,
            centroids,
            offsets,
            ids,
            consts,
            walk,
            members,
            terms,
            p,
            n_isects,
            votes.shape[0],
            tiles_wide,
            tiles_high,
            tile_size,
            map_pixels,
            map_width,
            cent_rows,
            pix_scale,
            LEVELS=levels,
            LP=lp,
            DIST=dist,
            IN_PIXELS=in_pixels,
            SAMPLED=sampled,
            PROJECT=2 if split else 1,
            **vote_kernel._walk_options(cap),
        )
        vote_kernel._launch(
            _fused_reduce_kernel,
            (1,),
            terms,
            vote,
            distortion,
            denominator,
            total,
            weighted,
            w_vote,
            w_dist,
            p,
            LEVELS=levels,
            LP=lp,
            RB=REDUCE_BLOCK,
            num_warps=4,
        )
    # in the order of the backward kernel's leading arguments
    saved = (*scene, pixel_xy, ids, consts, walk, members, terms, denominator)
    return (vote, distortion, total, weighted), saved


def _fused_backward(saved, modes, grads: Tuple[Optional[Tensor], Optional[Tensor], Optional[Tensor]], means_grad: bool):
    """The backward launch: (d loss / d votes [N, L, 3], d loss / d means [N, 3] when ``means_grad``) for the
    gradients ``grads`` = (of vote, of distortion, of total; None where none arrives); the support counted."""
    g_vote, g_distortion, g_total = grads
    votes, pixel_xy, denominator = saved[3], saved[6], saved[12]
    config, cap, _sampled, split, (w_vote, w_dist), support = modes
    levels, dist = config[0], config[1]
    n_isects = config[6]
    has_vote, has_total = g_vote is not None, g_total is not None
    has_distortion = g_distortion is not None and dist != 0
    g_votes = torch.zeros_like(votes)
    p = pixel_xy.shape[0]
    # the counts and stamps, or placeholders (never read) and a stamp of 0
    counts, stamps, stamp = support if support is not None else (denominator, denominator, 0)
    with vote_kernel._on(votes.device):
        vote_kernel._launch(
            _fused_bwd_kernel,
            (p,),
            *saved,
            # with strides: the gradient of a sum arrives expanded (stride 0), and copying it is a launch
            g_vote if has_vote else denominator,
            g_vote.stride(0) if has_vote else 0,
            g_distortion if has_distortion else denominator,
            g_distortion.stride(0) if has_distortion else 0,
            g_total if has_total else denominator,
            w_vote,
            w_dist,
            g_votes,
            counts,
            stamps,
            stamp,
            p,
            n_isects,
            votes.shape[0],
            LEVELS=levels,
            LP=vote_kernel._pow2(levels),
            DIST=dist,
            HAS_VOTE=has_vote,
            HAS_DIST=has_distortion,
            HAS_TOTAL=has_total,
            PROJECT=2 if split else 1,
            COUNT_SUPPORT=support is not None,
            **vote_kernel._walk_options(cap),
        )
    # d vote / d mean = identity at every level
    return g_votes, (g_votes.sum(1) if split and means_grad else None)


class _FusedVoteLosses(torch.autograd.Function):
    @staticmethod
    def forward(ctx, *inputs):
        outputs, saved = _fused_forward(*inputs)
        ctx.save_for_backward(*saved)
        ctx.modes = inputs[-1]  # its support counts are not saved tensors: the backward adds to them in place
        ctx.mark_non_differentiable(outputs[3])
        ctx.set_materialize_grads(False)
        return outputs

    @staticmethod
    def backward(ctx, g_vote, g_distortion, g_total, _g_weighted):
        none = (None,) * 16  # the forward's inputs after votes and means
        dist, split = ctx.modes[0][1], ctx.modes[3]
        wants_means = split and ctx.needs_input_grad[1]
        if g_distortion is not None and dist == 0:
            g_distortion = None
        if not (ctx.needs_input_grad[0] or wants_means) or all(g is None for g in (g_vote, g_distortion, g_total)):
            return (None, None) + none
        g_votes, g_means = _fused_backward(ctx.saved_tensors, ctx.modes, (g_vote, g_distortion, g_total), wants_means)
        return (g_votes if ctx.needs_input_grad[0] else None, g_means) + none


# Integer arguments that change from step to step (tile-list length, Gaussian count, pixel count). Triton
# otherwise specialises a kernel on whether each integer is divisible by 16 (or is 1) and compiles a new
# variant for every new combination: on a training run that was seconds of JIT in the first hundred vote
# steps. They only bound loops and clamp ids, so the hint buys nothing here.
_VARYING_INTS = ("n_pixels", "n_isects", "n_gauss")
# The same for what changes with the camera or the view (the tile grid, the vote maps' size and rows), and
# the tile size, so that start_warm_up's one-tile scene compiles the variant every training step runs.
_VIEW_INTS = ("tiles_wide", "tiles_high", "tile_size", "map_pixels", "map_width", "cent_rows")

if triton is not None:
    _program_pixel = vote_kernel._program_pixel
    _walk_block = vote_kernel._walk_block
    _entry_alpha = vote_kernel._entry_alpha
    _entry_depths = vote_kernel._entry_depths
    _compact = vote_kernel._compact
    _member_spread = vote_kernel._member_spread
    _compact_signs = vote_kernel._compact_signs
    _run_signs = vote_kernel._run_signs
    _sign = vote_kernel._sign

    @triton.jit
    def _floor_div(x, size):
        """floor(x / size) for a whole ``size``, exact even where float32 division is not correctly rounded:
        the quotient is corrected by the products, which are exact for whole numbers of tiles."""
        q = tl.floor(x / size)
        q = tl.where((q + 1.0) * size <= x, q + 1.0, q)
        return tl.where(q * size > x, q - 1.0, q)

    @triton.jit(do_not_specialize=_VARYING_INTS + _VIEW_INTS)
    def _fused_fwd_kernel(
        means_ptr,
        conics_ptr,
        opac_ptr,
        votes_ptr,
        vote_means_ptr,
        view_ptr,
        k_ptr,
        pix_ptr,
        target_ptr,
        valid_ptr,
        sample_ptr,
        voting_ptr,
        labels_ptr,
        cent_ptr,
        offsets_ptr,
        ids_ptr,
        consts_ptr,
        walk_ptr,
        members_ptr,
        terms_ptr,
        n_pixels,
        n_isects,
        n_gauss,
        tiles_wide,
        tiles_high,
        tile_size,
        map_pixels,
        map_width,
        cent_rows,
        pix_scale,
        LEVELS: tl.constexpr,
        LP: tl.constexpr,
        DIST: tl.constexpr,
        IN_PIXELS: tl.constexpr,
        SAMPLED: tl.constexpr,
        PROJECT: tl.constexpr,
        BLOCK: tl.constexpr,
        CAP: tl.constexpr,
        PB: tl.constexpr,
    ):
        """PROJECT 1: ``votes_ptr`` holds the votes; 2: the offsets, the votes being vote means + offsets."""
        pid, pix, walk = _program_pixel(pix_ptr, consts_ptr)
        lvl = tl.arange(0, LP)
        lvl_ok = lvl < LEVELS
        if SAMPLED:
            # vote_maps.pixels_and_targets for this program's drawn pixel, same float32 operations; the
            # position goes to pix_ptr for the backward and replaces the one _program_pixel read there (not
            # written yet: the load is unused and dropped)
            flat = tl.load(voting_ptr + tl.load(sample_ptr + pid)).to(tl.int64)
            flat = tl.minimum(tl.maximum(flat, 0), map_pixels - 1)
            row_index = flat // map_width
            px = ((flat - row_index * map_width).to(tl.float32) + 0.5) * pix_scale
            py = (row_index.to(tl.float32) + 0.5) * pix_scale
            tl.store(pix_ptr + 2 * pid, px)
            tl.store(pix_ptr + 2 * pid + 1, py)
            pix = (px, py, pix[2], pix[3])
            label = tl.load(labels_ptr + lvl * map_pixels + flat, mask=lvl_ok, other=0).to(tl.int64)
            label = tl.minimum(tl.maximum(label, 0), cent_rows - 1)
            centroid_x = tl.load(cent_ptr + (lvl * cent_rows + label) * 2, mask=lvl_ok, other=0.0)
            centroid_y = tl.load(cent_ptr + (lvl * cent_rows + label) * 2 + 1, mask=lvl_ok, other=0.0)
            # finite centroid <=> the pixel votes at that level (NaN and inf give NaN here)
            sampled_valid = lvl_ok & ((centroid_x - centroid_x) == 0.0)
            sampled_target_x = (centroid_x + 0.5) * pix_scale
            sampled_target_y = (centroid_y + 0.5) * pix_scale
        px, py, _alpha_max, _alpha_min = pix
        near = tl.load(consts_ptr + 5)

        # the pixel's tile run (vote_render._pixel_runs): empty outside the grid (NaN compares False)
        tile_x = _floor_div(px, tile_size)
        tile_y = _floor_div(py, tile_size)
        in_grid = (tile_x >= 0.0) & (tile_x < tiles_wide) & (tile_y >= 0.0) & (tile_y < tiles_high)
        tile = tl.where(in_grid, tile_y * tiles_wide + tile_x, 0.0).to(tl.int64)
        tiles = tiles_wide * tiles_high
        start = tl.load(offsets_ptr + tile, mask=in_grid, other=0).to(tl.int64)
        has_next = in_grid & (tile + 1 < tiles)
        end = tl.load(offsets_ptr + tile + 1, mask=has_next, other=n_isects).to(tl.int64)
        start = tl.minimum(tl.maximum(start, 0), n_isects)
        end = tl.where(in_grid, tl.minimum(tl.maximum(end, start), n_isects), start)

        lane = tl.arange(0, BLOCK).to(tl.int64)
        r20 = tl.load(view_ptr + 8)
        r21 = tl.load(view_ptr + 9)
        r22 = tl.load(view_ptr + 10)
        t2 = tl.load(view_ptr + 11)
        geo = (means_ptr, conics_ptr, opac_ptr, ids_ptr, n_gauss)
        zsrc = (votes_ptr, r20, r21, r22, t2, vote_means_ptr)
        member_row = members_ptr + pid * CAP

        t = px * 0.0 + 1.0
        count = tl.sum(lane * 0, axis=0).to(tl.int32)
        last = start * 0 - 1
        sx = tl.zeros([LP], dtype=px.dtype)
        sy = tl.zeros([LP], dtype=px.dtype)
        sz = tl.zeros([LP], dtype=px.dtype)
        zacc = tl.zeros([LP], dtype=px.dtype)
        pos = start
        walking = pos < end
        while walking:
            gid, _alpha, member, _t_before, t, last, pos, walking = _walk_block(
                geo, pos, end, pix, walk, t, last, BLOCK
            )
            depth, x, y, z = _entry_depths(zsrc, PROJECT, gid, member, lvl, LEVELS)
            sx += tl.sum(x, axis=0)
            sy += tl.sum(y, axis=0)
            sz += tl.sum(z, axis=0)
            zacc += tl.sum(depth, axis=0)
            slot, count = _compact(member, count)
            tl.store(member_row + slot, gid.to(tl.int32), mask=member & (slot < CAP))

        n_members = tl.maximum(count, 1).to(px.dtype)
        # uniform mean (Eq. 8), to the camera, projected (Eq. 9): vote_render._finish / project_to_pixels
        mx = sx / n_members
        my = sy / n_members
        mz = sz / n_members
        v00 = tl.load(view_ptr + 0)
        v01 = tl.load(view_ptr + 1)
        v02 = tl.load(view_ptr + 2)
        v10 = tl.load(view_ptr + 4)
        v11 = tl.load(view_ptr + 5)
        v12 = tl.load(view_ptr + 6)
        cam_x = mx * v00 + my * v01 + mz * v02 + tl.load(view_ptr + 3)
        cam_y = mx * v10 + my * v11 + mz * v12 + tl.load(view_ptr + 7)
        cam_z = mx * r20 + my * r21 + mz * r22 + t2
        zc = tl.maximum(cam_z, near)
        u = cam_x / zc
        w = cam_y / zc
        k00 = tl.load(k_ptr + 0)
        k01 = tl.load(k_ptr + 1)
        k10 = tl.load(k_ptr + 3)
        k11 = tl.load(k_ptr + 4)
        proj_x = u * k00 + w * k01 + tl.load(k_ptr + 2)
        proj_y = u * k10 + w * k11 + tl.load(k_ptr + 5)
        # vote loss (Eq. 10) at the used levels: valid and a non-empty voting set
        if SAMPLED:
            used = sampled_valid & (count > 0)
            target_x = tl.where(used, sampled_target_x, 0.0)
            target_y = tl.where(used, sampled_target_y, 0.0)
        else:
            used = (tl.load(valid_ptr + pid * LEVELS + lvl, mask=lvl_ok, other=0) != 0) & (count > 0)
            target_x = tl.load(target_ptr + pid * (2 * LEVELS) + 2 * lvl, mask=used, other=0.0)
            target_y = tl.load(target_ptr + pid * (2 * LEVELS) + 2 * lvl + 1, mask=used, other=0.0)
        error_x = proj_x - target_x
        error_y = proj_y - target_y
        error = tl.where(used, tl.abs(error_x) + tl.abs(error_y), 0.0)
        # its gradient with respect to each member's vote (1 / |M| of the mean's): sign(0) = 0 as torch's abs
        sign_x = _sign(error_x)
        sign_y = _sign(error_y)
        g_u = k00 * sign_x + k10 * sign_y
        g_w = k01 * sign_x + k11 * sign_y
        g_cam_x = g_u / zc
        g_cam_y = g_w / zc
        # clamp_min passes the gradient where cam_z >= near
        g_cam_z = tl.where(cam_z >= near, -(g_u * cam_x + g_w * cam_y) / (zc * zc), 0.0)
        scale = tl.where(used, 1.0 / n_members, 0.0)
        jac_x = (v00 * g_cam_x + v10 * g_cam_y + r20 * g_cam_z) * scale
        jac_y = (v01 * g_cam_x + v11 * g_cam_y + r21 * g_cam_z) * scale
        jac_z = (v02 * g_cam_x + v12 * g_cam_y + r22 * g_cam_z) * scale

        # depth distortion (Eq. 12) over the members' depths, and d distortion / d depth = factor * s_i
        # (s_i = sum_j sign(z_i - z_j) for l1, z_i - mean for squared)
        mean_z = zacc / n_members
        distortion = tl.zeros([LP], dtype=px.dtype)
        factor = tl.zeros([LP], dtype=px.dtype)
        if DIST != 0:
            runs = (geo, pix, zsrc, start, last + 1)
            spread = _member_spread(member_row, count, mean_z, runs, lvl, LEVELS, PROJECT, DIST, BLOCK, CAP, PB)
            if DIST == 1:
                distortion = spread
                factor = spread * 0.0 + 1.0
                if IN_PIXELS:
                    # the mean pairwise gap in pixels at the members' mean depth, that scale held constant
                    pairs = tl.maximum(n_members * (n_members - 1.0) / 2.0, 1.0)
                    per_unit = tl.sqrt(k00 * k11) / tl.maximum(mean_z, near)
                    distortion = spread / pairs * per_unit
                    factor = per_unit / pairs
            if DIST == 2:
                distortion = count.to(px.dtype) * spread
                factor = spread * 0.0 + 2.0 * count.to(px.dtype)
            distortion = tl.where(used, distortion, 0.0)
            factor = tl.where(used, factor, 0.0)

        tl.store(walk_ptr + pid, count.to(tl.int64))
        tl.store(walk_ptr + n_pixels + pid, start)
        tl.store(walk_ptr + 2 * n_pixels + pid, last)
        row = terms_ptr + pid * (8 * LEVELS) + lvl
        tl.store(row, error, mask=lvl_ok)
        tl.store(row + LEVELS, distortion, mask=lvl_ok)
        tl.store(row + 2 * LEVELS, used.to(px.dtype), mask=lvl_ok)
        tl.store(row + 3 * LEVELS, jac_x, mask=lvl_ok)
        tl.store(row + 4 * LEVELS, jac_y, mask=lvl_ok)
        tl.store(row + 5 * LEVELS, jac_z, mask=lvl_ok)
        tl.store(row + 6 * LEVELS, factor, mask=lvl_ok)
        tl.store(row + 7 * LEVELS, mean_z, mask=lvl_ok)

    @triton.jit(do_not_specialize=("n_pixels",))
    def _fused_reduce_kernel(
        terms_ptr,
        vote_ptr,
        dist_ptr,
        den_ptr,
        total_ptr,
        weighted_ptr,
        w_vote,
        w_dist,
        n_pixels,
        LEVELS: tl.constexpr,
        LP: tl.constexpr,
        RB: tl.constexpr,
    ):
        """Per level: the means of the vote L1 and of the distortion over the used pixels (vote_losses); and
        w_vote * (sum over levels of the first) + w_dist * (of the second), and these two terms."""
        lvl = tl.arange(0, LP)
        lvl_ok = lvl < LEVELS
        rows = tl.arange(0, RB).to(tl.int64)
        first = tl.load(terms_ptr + lvl, mask=lvl_ok, other=0.0)
        error = first * 0.0
        distortion = first * 0.0
        used = first * 0.0
        for p0 in range(0, n_pixels, RB):
            r = p0 + rows
            mask = (r < n_pixels)[:, None] & lvl_ok[None, :]
            at = terms_ptr + r[:, None] * (8 * LEVELS) + lvl[None, :]
            error += tl.sum(tl.load(at, mask=mask, other=0.0), axis=0)
            distortion += tl.sum(tl.load(at + LEVELS, mask=mask, other=0.0), axis=0)
            used += tl.sum(tl.load(at + 2 * LEVELS, mask=mask, other=0.0), axis=0)
        denominator = tl.maximum(used, 1.0)
        vote = error / denominator
        distortion = distortion / denominator
        tl.store(vote_ptr + lvl, vote, mask=lvl_ok)
        tl.store(dist_ptr + lvl, distortion, mask=lvl_ok)
        tl.store(den_ptr + lvl, denominator, mask=lvl_ok)
        vote_term = w_vote * tl.sum(tl.where(lvl_ok, vote, 0.0), axis=0)
        dist_term = w_dist * tl.sum(tl.where(lvl_ok, distortion, 0.0), axis=0)
        tl.store(total_ptr, vote_term + dist_term)
        tl.store(weighted_ptr, vote_term)
        tl.store(weighted_ptr + 1, dist_term)

    @triton.jit(do_not_specialize=_VARYING_INTS + ("stamp",))
    def _fused_bwd_kernel(
        means_ptr,
        conics_ptr,
        opac_ptr,
        votes_ptr,
        vote_means_ptr,
        view_ptr,
        pix_ptr,
        ids_ptr,
        consts_ptr,
        walk_ptr,
        members_ptr,
        terms_ptr,
        den_ptr,
        g_vote_ptr,
        g_vote_stride,
        g_dist_ptr,
        g_dist_stride,
        g_total_ptr,
        w_vote,
        w_dist,
        g_votes_ptr,
        counts_ptr,
        stamps_ptr,
        stamp,
        n_pixels,
        n_isects,
        n_gauss,
        LEVELS: tl.constexpr,
        LP: tl.constexpr,
        DIST: tl.constexpr,
        HAS_VOTE: tl.constexpr,
        HAS_DIST: tl.constexpr,
        HAS_TOTAL: tl.constexpr,
        PROJECT: tl.constexpr,
        COUNT_SUPPORT: tl.constexpr,
        BLOCK: tl.constexpr,
        CAP: tl.constexpr,
        PB: tl.constexpr,
    ):
        pid = tl.program_id(0).to(tl.int64)
        count = tl.load(walk_ptr + pid)
        if count > 0:
            lvl = tl.arange(0, LP)
            lvl_ok = lvl < LEVELS
            row = terms_ptr + pid * (8 * LEVELS) + lvl
            denominator = tl.load(den_ptr + lvl, mask=lvl_ok, other=1.0)
            g_mean_x = tl.zeros([LP], dtype=denominator.dtype)
            g_mean_y = tl.zeros([LP], dtype=denominator.dtype)
            g_mean_z = tl.zeros([LP], dtype=denominator.dtype)
            # the total's gradient reaches each level's vote and distortion times their weight
            g_total = tl.zeros([LP], dtype=denominator.dtype)
            if HAS_TOTAL:
                g_total += tl.load(g_total_ptr)
            if HAS_VOTE or HAS_TOTAL:
                g_vote = tl.zeros([LP], dtype=denominator.dtype)
                if HAS_VOTE:
                    g_vote += tl.load(g_vote_ptr + lvl * g_vote_stride, mask=lvl_ok, other=0.0)
                if HAS_TOTAL:
                    g_vote += w_vote * g_total
                g_vote = g_vote / denominator
                g_mean_x = g_vote * tl.load(row + 3 * LEVELS, mask=lvl_ok, other=0.0)
                g_mean_y = g_vote * tl.load(row + 4 * LEVELS, mask=lvl_ok, other=0.0)
                g_mean_z = g_vote * tl.load(row + 5 * LEVELS, mask=lvl_ok, other=0.0)
            g_depth = tl.zeros([LP], dtype=denominator.dtype)
            if DIST != 0 and (HAS_DIST or HAS_TOTAL):
                g_dist = tl.zeros([LP], dtype=denominator.dtype)
                if HAS_DIST:
                    g_dist += tl.load(g_dist_ptr + lvl * g_dist_stride, mask=lvl_ok, other=0.0)
                if HAS_TOTAL:
                    g_dist += w_dist * g_total
                g_dist = g_dist / denominator
                g_depth = g_dist * tl.load(row + 6 * LEVELS, mask=lvl_ok, other=0.0)
            # the levels whose members get a gradient from this pixel
            live = lvl_ok & ((g_mean_x != 0.0) | (g_mean_y != 0.0) | (g_mean_z != 0.0) | (g_depth != 0.0))
            mean_z = tl.load(row + 7 * LEVELS, mask=lvl_ok, other=0.0)
            r20 = tl.load(view_ptr + 8)
            r21 = tl.load(view_ptr + 9)
            r22 = tl.load(view_ptr + 10)
            t2 = tl.load(view_ptr + 11)
            zsrc = (votes_ptr, r20, r21, r22, t2, vote_means_ptr)
            if count <= CAP:
                member_row = members_ptr + pid * CAP
                r = tl.arange(0, PB)
                for i0 in range(0, count, PB):
                    ri = i0 + r
                    ok = ri < count
                    gid = tl.load(member_row + ri, mask=ok, other=0).to(tl.int64)
                    s = tl.zeros([PB, LP], dtype=denominator.dtype)
                    if DIST != 0 and (HAS_DIST or HAS_TOTAL):
                        # the members' depths as the walk computed them (the same bits)
                        z_i, _x, _y, _z = _entry_depths(zsrc, PROJECT, gid, ok, lvl, LEVELS)
                        if DIST == 1:
                            s = _compact_signs(z_i, member_row, count, zsrc, lvl, LEVELS, PROJECT, PB)
                        if DIST == 2:
                            s = z_i - mean_z[None, :]
                    _scatter_vote_grads(
                        g_votes_ptr, gid, ok, lvl, LEVELS, g_mean_x, g_mean_y, g_mean_z, g_depth, s, r20, r21, r22
                    )
                    if COUNT_SUPPORT:
                        _count_support(counts_ptr, stamps_ptr, stamp, gid, ok, lvl, LEVELS, live)
            else:
                # more than CAP members: walk [start, last] again; its visible entries are the members
                _pid, pix, _walk = _program_pixel(pix_ptr, consts_ptr)
                geo = (means_ptr, conics_ptr, opac_ptr, ids_ptr, n_gauss)
                start = tl.load(walk_ptr + n_pixels + pid)
                stop = tl.load(walk_ptr + 2 * n_pixels + pid) + 1
                runs = (geo, pix, zsrc, start, stop)
                lane = tl.arange(0, BLOCK).to(tl.int64)
                for p0 in range(start, stop, BLOCK):
                    offs_i = p0 + lane
                    gid, _a, vis_i, _dx, _dy, _ca, _cb, _cc, _f, _r = _entry_alpha(geo, offs_i, stop, pix)
                    z_i, _x, _y, _z = _entry_depths(zsrc, PROJECT, gid, vis_i, lvl, LEVELS)
                    s = tl.zeros([BLOCK, LP], dtype=denominator.dtype)
                    if DIST != 0 and (HAS_DIST or HAS_TOTAL):
                        if DIST == 2:
                            s = z_i - mean_z[None, :]
                        if DIST == 1:
                            s = _run_signs(z_i, runs, lvl, LEVELS, PROJECT, BLOCK)
                    _scatter_vote_grads(
                        g_votes_ptr, gid, vis_i, lvl, LEVELS, g_mean_x, g_mean_y, g_mean_z, g_depth, s, r20, r21, r22
                    )
                    if COUNT_SUPPORT:
                        _count_support(counts_ptr, stamps_ptr, stamp, gid, vis_i, lvl, LEVELS, live)

    @triton.jit
    def _scatter_vote_grads(
        g_votes_ptr, gid, ok, lvl, LEVELS: tl.constexpr, g_mean_x, g_mean_y, g_mean_z, g_depth, s, r20, r21, r22
    ):
        """Add, for members ``gid`` [B] and every level, the mean vote's gradient plus the depth term
        g_depth * s (s [B, LP]) along d depth / d vote = viewmat[2, :3]."""
        mask = ok[:, None] & (lvl < LEVELS)[None, :]
        at = g_votes_ptr + gid[:, None] * (LEVELS * 3) + lvl[None, :] * 3
        term = g_depth[None, :] * s
        tl.atomic_add(at, g_mean_x[None, :] + term * r20, mask=mask, sem="relaxed")
        tl.atomic_add(at + 1, g_mean_y[None, :] + term * r21, mask=mask, sem="relaxed")
        tl.atomic_add(at + 2, g_mean_z[None, :] + term * r22, mask=mask, sem="relaxed")

    @triton.jit
    def _count_support(counts_ptr, stamps_ptr, stamp, gid, ok, lvl, LEVELS: tl.constexpr, live):
        """counts[gid, l] += 1 for members ``gid`` [B] at the ``live`` [LP] levels, unless stamps[gid, l] is
        already ``stamp`` (counted in this step, by this pixel or another)."""
        mask = ok[:, None] & live[None, :]
        at = gid[:, None] * LEVELS + lvl[None, :]
        before = tl.atomic_xchg(stamps_ptr + at, stamp, mask=mask, sem="relaxed")
        tl.atomic_add(counts_ptr + at, 1.0, mask=mask & (before != stamp), sem="relaxed")
