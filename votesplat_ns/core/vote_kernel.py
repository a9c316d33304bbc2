"""Fused vote pass in Triton: one launch for the forward of every level, one for the backward.

Same membership rule, levels and ablation switches as :mod:`votesplat_ns.core.vote_render` (read
its module docstring); this module only replaces the walk and the blending sums of
``render_votes_tiled``. The torch code keeps what is cheap and per pixel or per Gaussian:
the vote table (``_vote_table``: world vote, its projection for 2D blending, its camera depth)
before the kernel, and normalisation, projection and the distortion's final scaling
(``_finish``) after it, so gradients reach votes, viewmat and K through plain autograd.

What a kernel program does (one program per sampled pixel):

* forward: walks the pixel's tile run front to back in blocks of ``BLOCK`` entries, carrying
  the transmittance across blocks (inclusive ``cumprod`` within a block; the transmittance in
  front of an entry is the inclusive product divided by its own 1 - alpha, exact to an ulp,
  and VOTE_THRESHOLD_RTOL absorbs that ulp at the threshold). It stops once the
  transmittance is at or below both the voting threshold and the colour stop, or the run
  ends. It sums, over the voting set M, the weights, the weighted table rows of every
  level, and the member depths; it records |M| and the run position of the last member.
  Every visible entry up to the last member is a member (the transmittance only falls), so
  a second pass over [run start, last member] knows M without storing it: it computes the
  depth spread, sum_{i<j} |z_i - z_j| over pairs of blocks ("l1", "l1_pixels") or
  sum_i (z_i - mean)^2 ("squared").
* backward: re-walks [run start, last member] and scatters, with atomic adds, the gradient
  of every member's table row (weight x row gradient, plus the depth term: sum_j
  sign(z_i - z_j) or 2 (z_i - mean)) and, for alpha*T weights with geometry gradients, of
  its means2d, conic and opacity: a second walk, back to front as gsplat's backward, carries
  the suffix sum of g_w * w over later members, through which their transmittance depends
  on this alpha.

A program's work is a few blocks of gathers, so at training sizes the torch ops around the
two launches (input checks, vote table, normalisation, losses) are expected to cost about as
much as the kernels (an estimate: bench-vote measures the whole pass).

Why Triton rather than CUDA C++ next to gsplat's extension: Triton ships with torch's CUDA
wheels, so there is no build step and no compiler to match; the kernels JIT-compile on the
first call for each (dtype, levels, switches) combination and are cached on disk
(``~/.triton/cache``); the bench-vote stage prints that first-call time. Its CPU interpreter
(``TRITON_INTERPRET=1``) also runs these kernels on CPU tensors, so the tests check them
without a GPU.
"""

from __future__ import annotations

import contextlib
import os
from typing import Optional, Tuple

import torch
from torch import Tensor

# pyright: reportOptionalMemberAccess=false, reportInvalidTypeForm=false
# (triton is optional: ``tl`` is None without it, and the kernels' ``tl.constexpr`` parameter
# annotations are Triton's own markers, not Python types; both are only reached with triton.)

try:  # optional: the torch path works without it
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - depends on the environment
    triton = None
    tl = None

# Entries of a tile run per block of the walk, and warps per program. Not tuned on a device yet.
# The gradient scatters use relaxed atomics: only the sums matter, no ordering between programs.
BLOCK = 32
NUM_WARPS = 2
_DIST_MODES = {"none": 0, "l1": 1, "l1_pixels": 1, "squared": 2}


def interpreter_enabled() -> bool:
    return os.environ.get("TRITON_INTERPRET", "0") == "1"


def unavailable_reason(device: torch.device) -> Optional[str]:
    """None when the kernels can run on ``device``, else why not (one line)."""
    if triton is None:
        return "triton is not installed (it ships with torch's CUDA wheels)"
    if device.type == "cuda":
        return None
    if device.type == "cpu" and interpreter_enabled():
        return None
    return f"the Triton vote kernels run on CUDA tensors (or on CPU under TRITON_INTERPRET=1), got {device.type}"


def vote_sums(
    geometry: Tensor,
    vote_table: Tensor,
    pixel_xy: Tensor,
    run_start: Tensor,
    run_end: Tensor,
    flatten_ids: Tensor,
    threshold: float,
    open_above: float,
    alpha_min: float,
    colour_stop: float,
    alpha_max: float,
    alpha_t: bool,
    distortion: str,
) -> Tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Per-pixel sums over the voting set, from the tile runs.

    Args:
        geometry [N, 6]: means2d, conic (a, b, c), opacity; differentiable when it requires grad
            and ``alpha_t`` (uniform weights do not depend on the geometry).
        vote_table [N, L, D + 1]: per Gaussian and level the D values to blend, then the vote's
            camera depth (``vote_render._vote_table``).
        pixel_xy [P, 2] (no gradient), run_start / run_end [P]: each pixel's run in flatten_ids.
        threshold: the voting threshold with its relative slack; open_above: the
            transmittance below which no later entry can join M.

    Returns (count [P] int64, weight_sum [P], value_sum [P, L, D], depth_sum [P, L],
    spread [P, L]) where spread is sum_{i<j} |z_i - z_j| (distortion "l1"/"l1_pixels"),
    sum_i (z_i - mean)^2 ("squared") or 0 ("none"); depth_sum (sum of member depths) and
    count carry no gradient.
    """
    n, levels, width = vote_table.shape
    dtype = vote_table.dtype
    consts = _constants((threshold, alpha_max, open_above, alpha_min, colour_stop), dtype, vote_table.device)
    config = (levels, width, bool(alpha_t), _DIST_MODES[distortion])
    count, weight_sum, value_sum, depth_sum, spread = _VoteSums.apply(
        geometry.contiguous(),
        vote_table.contiguous(),
        pixel_xy.detach().contiguous(),
        run_start.contiguous(),
        run_end.contiguous(),
        flatten_ids.contiguous(),
        consts,
        config,
    )
    value_sum = value_sum.view(-1, levels, width)[..., : width - 1]
    return count.long(), weight_sum, value_sum, depth_sum, spread


_CONSTANTS = {}


def _constants(values: Tuple[float, ...], dtype: torch.dtype, device: torch.device) -> Tensor:
    """The walk's constants in the data's dtype (compared as torch compares them), put on the device once:
    a fresh host-to-device copy each call would stall the step, and a Python float argument is float32."""
    key = (values, dtype, device)
    if key not in _CONSTANTS:
        _CONSTANTS[key] = torch.tensor(values, dtype=dtype, device=device)
    return _CONSTANTS[key]


def _on(device: torch.device):
    """Triton launches on the current CUDA device: make it the tensors' one."""
    return torch.cuda.device(device) if device.type == "cuda" else contextlib.nullcontext()


def _pow2(x: int) -> int:
    return 1 << max(0, (int(x) - 1).bit_length())


class _VoteSums(torch.autograd.Function):
    @staticmethod
    def forward(ctx, geometry, table, pixel_xy, run_start, run_end, flatten_ids, consts, config):
        levels, width, alpha_t, dist = config
        p = pixel_xy.shape[0]
        device, dtype = table.device, table.dtype
        count = torch.empty(p, dtype=torch.int32, device=device)
        last = torch.empty(p, dtype=torch.int64, device=device)
        weight_sum = torch.empty(p, dtype=dtype, device=device)
        value_sum = torch.empty(p, levels * width, dtype=dtype, device=device)
        depth_sum = torch.empty(p, levels, dtype=dtype, device=device)
        spread = torch.empty(p, levels, dtype=dtype, device=device)
        if p > 0:
            with _on(device):
                _vote_fwd_kernel[(p,)](
                    geometry,
                    table,
                    pixel_xy,
                    run_start,
                    run_end,
                    flatten_ids,
                    consts,
                    count,
                    last,
                    weight_sum,
                    value_sum,
                    depth_sum,
                    spread,
                    LEVELS=levels,
                    LP=_pow2(levels),
                    D1=width,
                    LDP=_pow2(levels * width),
                    ALPHA_T=alpha_t,
                    DIST=dist,
                    BLOCK=BLOCK,
                    num_warps=NUM_WARPS,  # pyright: ignore[reportCallIssue]  (a launch option of triton's grid call)
                )
        ctx.save_for_backward(geometry, table, pixel_xy, run_start, flatten_ids, consts, count, last, depth_sum)
        ctx.config = config
        ctx.mark_non_differentiable(count, depth_sum)
        return count, weight_sum, value_sum, depth_sum, spread

    @staticmethod
    def backward(ctx, _g_count, g_weight_sum, g_value_sum, _g_depth_sum, g_spread):
        geometry, table, pixel_xy, run_start, flatten_ids, consts, count, last, depth_sum = ctx.saved_tensors
        levels, width, alpha_t, dist = ctx.config
        p = pixel_xy.shape[0]
        geometry_grad = alpha_t and ctx.needs_input_grad[0]
        if not (ctx.needs_input_grad[1] or geometry_grad) or p == 0:
            return None, None, None, None, None, None, None, None

        def dense(g, shape):
            return torch.zeros(shape, dtype=table.dtype, device=table.device) if g is None else g.contiguous()

        g_weight_sum = dense(g_weight_sum, (p,))
        g_value_sum = dense(g_value_sum, (p, levels * width))
        g_spread = dense(g_spread, (p, levels))
        g_table = torch.zeros_like(table)
        g_geometry = torch.zeros_like(geometry) if geometry_grad else g_table  # a dummy pointer when unused
        with _on(table.device):
            _vote_bwd_kernel[(p,)](
                geometry,
                table,
                pixel_xy,
                run_start,
                last,
                count,
                depth_sum,
                flatten_ids,
                consts,
                g_weight_sum,
                g_value_sum,
                g_spread,
                g_table,
                g_geometry,
                LEVELS=levels,
                LP=_pow2(levels),
                D1=width,
                LDP=_pow2(levels * width),
                ALPHA_T=alpha_t,
                DIST=dist,
                GEOMETRY_GRAD=geometry_grad,
                BLOCK=BLOCK,
                num_warps=NUM_WARPS,  # pyright: ignore[reportCallIssue]  (a launch option of triton's grid call)
            )
        return (
            g_geometry if geometry_grad else None,
            g_table if ctx.needs_input_grad[1] else None,
            None,
            None,
            None,
            None,
            None,
            None,
        )


if triton is not None:

    @triton.jit
    def _block_alpha(geom_ptr, ids_ptr, offs, stop, px, py, alpha_max, alpha_min):
        """gsplat's alpha at (px, py) for run entries ``offs`` (those >= stop are out), and visibility."""
        inside = offs < stop
        gid = tl.load(ids_ptr + offs, mask=inside, other=0).to(tl.int64)
        base = gid * 6
        mx = tl.load(geom_ptr + base, mask=inside, other=0.0)
        my = tl.load(geom_ptr + base + 1, mask=inside, other=0.0)
        ca = tl.load(geom_ptr + base + 2, mask=inside, other=0.0)
        cb = tl.load(geom_ptr + base + 3, mask=inside, other=0.0)
        cc = tl.load(geom_ptr + base + 4, mask=inside, other=0.0)
        opacity = tl.load(geom_ptr + base + 5, mask=inside, other=0.0)
        dx = mx - px
        dy = my - py
        # the operation order of vote_render._alpha
        sigma = cb * dx * dy + 0.5 * (dx * dx * ca + dy * dy * cc)
        falloff = tl.exp(-tl.maximum(sigma, 0.0))
        raw = opacity * falloff
        alpha = tl.minimum(raw, alpha_max)
        visible = inside & (sigma >= 0.0) & (alpha >= alpha_min)
        return gid, alpha, visible, dx, dy, ca, cb, cc, falloff, raw

    @triton.jit
    def _vote_fwd_kernel(
        geom_ptr,
        table_ptr,
        pix_ptr,
        start_ptr,
        end_ptr,
        ids_ptr,
        consts_ptr,
        count_ptr,
        last_ptr,
        wsum_ptr,
        vsum_ptr,
        zsum_ptr,
        spread_ptr,
        LEVELS: tl.constexpr,
        LP: tl.constexpr,
        D1: tl.constexpr,
        LDP: tl.constexpr,
        ALPHA_T: tl.constexpr,
        DIST: tl.constexpr,
        BLOCK: tl.constexpr,
    ):
        pid = tl.program_id(0).to(tl.int64)
        px = tl.load(pix_ptr + 2 * pid)
        py = tl.load(pix_ptr + 2 * pid + 1)
        start = tl.load(start_ptr + pid).to(tl.int64)
        end = tl.load(end_ptr + pid).to(tl.int64)
        threshold = tl.load(consts_ptr)
        alpha_max = tl.load(consts_ptr + 1)
        open_above = tl.load(consts_ptr + 2)
        alpha_min = tl.load(consts_ptr + 3)
        colour_stop = tl.load(consts_ptr + 4)
        LD1: tl.constexpr = LEVELS * D1
        lane = tl.arange(0, BLOCK).to(tl.int64)
        cols = tl.arange(0, LDP)
        col_ok = cols < LD1
        lvl = tl.arange(0, LP)
        lvl_ok = lvl < LEVELS

        one = px * 0.0 + 1.0
        t = one
        count = tl.sum(lane * 0, axis=0).to(tl.int32)
        last = start * 0 - 1
        wsum = one * 0.0
        vacc = tl.zeros([LDP], dtype=px.dtype)
        zacc = tl.zeros([LP], dtype=px.dtype)
        pos = start
        walking = pos < end
        while walking:
            offs = pos + lane
            gid, alpha, visible, _dx, _dy, _a, _b, _c, _f, _r = _block_alpha(
                geom_ptr, ids_ptr, offs, end, px, py, alpha_max, alpha_min
            )
            keep = 1.0 - tl.where(visible, alpha, 0.0)
            t_after = t * tl.cumprod(keep, axis=0)
            t_before = t_after / keep
            member = visible & (t_after > colour_stop) & (t_before > threshold)
            count += tl.sum(member.to(tl.int32), axis=0)
            last = tl.maximum(last, tl.max(tl.where(member, offs, -1), axis=0))
            if ALPHA_T:
                w = tl.where(member, alpha * t_before, 0.0)
            else:
                w = member.to(px.dtype)
            wsum += tl.sum(w, axis=0)
            rows = tl.load(
                table_ptr + gid[:, None] * LD1 + cols[None, :], mask=member[:, None] & col_ok[None, :], other=0.0
            )
            vacc += tl.sum(w[:, None] * rows, axis=0)
            depth = tl.load(
                table_ptr + gid[:, None] * LD1 + lvl[None, :] * D1 + (D1 - 1),
                mask=member[:, None] & lvl_ok[None, :],
                other=0.0,
            )
            zacc += tl.sum(depth, axis=0)
            t = tl.min(t_after, axis=0)
            pos += BLOCK
            walking = (pos < end) & (t > open_above)

        # M = the visible entries in [start, last]
        stop = last + 1
        spread = tl.zeros([LP], dtype=px.dtype)
        if DIST == 2:
            mean = zacc / tl.maximum(count, 1).to(px.dtype)
            for p0 in range(start, stop, BLOCK):
                offs = p0 + lane
                gid, _al, visible, _dx, _dy, _a, _b, _c, _f, _r = _block_alpha(
                    geom_ptr, ids_ptr, offs, stop, px, py, alpha_max, alpha_min
                )
                depth = tl.load(
                    table_ptr + gid[:, None] * LD1 + lvl[None, :] * D1 + (D1 - 1),
                    mask=visible[:, None] & lvl_ok[None, :],
                    other=0.0,
                )
                deviation = tl.where(visible[:, None] & lvl_ok[None, :], depth - mean[None, :], 0.0)
                spread += tl.sum(deviation * deviation, axis=0)
        if DIST == 1:
            for p0 in range(start, stop, BLOCK):
                offs_i = p0 + lane
                gid_i, _al, vis_i, _dx, _dy, _a, _b, _c, _f, _r = _block_alpha(
                    geom_ptr, ids_ptr, offs_i, stop, px, py, alpha_max, alpha_min
                )
                for q0 in range(p0, stop, BLOCK):
                    offs_j = q0 + lane
                    gid_j, _al2, vis_j, _dx2, _dy2, _a2, _b2, _c2, _f2, _r2 = _block_alpha(
                        geom_ptr, ids_ptr, offs_j, stop, px, py, alpha_max, alpha_min
                    )
                    pair = vis_i[:, None] & vis_j[None, :] & (offs_i[:, None] < offs_j[None, :])
                    for level in range(LEVELS):
                        z_i = tl.load(table_ptr + gid_i * LD1 + level * D1 + (D1 - 1), mask=vis_i, other=0.0)
                        z_j = tl.load(table_ptr + gid_j * LD1 + level * D1 + (D1 - 1), mask=vis_j, other=0.0)
                        gap = tl.where(pair, tl.abs(z_i[:, None] - z_j[None, :]), 0.0)
                        spread += tl.where(lvl == level, tl.sum(tl.sum(gap, axis=1), axis=0), 0.0)

        tl.store(count_ptr + pid, count)
        tl.store(last_ptr + pid, last)
        tl.store(wsum_ptr + pid, wsum)
        tl.store(vsum_ptr + pid * LD1 + cols, vacc, mask=col_ok)
        tl.store(zsum_ptr + pid * LEVELS + lvl, zacc, mask=lvl_ok)
        tl.store(spread_ptr + pid * LEVELS + lvl, spread, mask=lvl_ok)

    @triton.jit
    def _vote_bwd_kernel(
        geom_ptr,
        table_ptr,
        pix_ptr,
        start_ptr,
        last_ptr,
        count_ptr,
        zsum_ptr,
        ids_ptr,
        consts_ptr,
        g_wsum_ptr,
        g_vsum_ptr,
        g_spread_ptr,
        g_table_ptr,
        g_geom_ptr,
        LEVELS: tl.constexpr,
        LP: tl.constexpr,
        D1: tl.constexpr,
        LDP: tl.constexpr,
        ALPHA_T: tl.constexpr,
        DIST: tl.constexpr,
        GEOMETRY_GRAD: tl.constexpr,
        BLOCK: tl.constexpr,
    ):
        pid = tl.program_id(0).to(tl.int64)
        px = tl.load(pix_ptr + 2 * pid)
        py = tl.load(pix_ptr + 2 * pid + 1)
        start = tl.load(start_ptr + pid).to(tl.int64)
        stop = tl.load(last_ptr + pid) + 1
        count = tl.load(count_ptr + pid)
        alpha_max = tl.load(consts_ptr + 1)
        alpha_min = tl.load(consts_ptr + 3)
        LD1: tl.constexpr = LEVELS * D1
        lane = tl.arange(0, BLOCK).to(tl.int64)
        cols = tl.arange(0, LDP)
        col_ok = cols < LD1
        value_col = col_ok & ((cols % D1) != (D1 - 1))
        lvl = tl.arange(0, LP)
        lvl_ok = lvl < LEVELS
        g_wsum = tl.load(g_wsum_ptr + pid)
        g_row = tl.load(g_vsum_ptr + pid * LD1 + cols, mask=value_col, other=0.0)
        g_spread = tl.load(g_spread_ptr + pid * LEVELS + lvl, mask=lvl_ok, other=0.0)
        one = px * 0.0 + 1.0

        if DIST == 2:
            mean = tl.load(zsum_ptr + pid * LEVELS + lvl, mask=lvl_ok, other=0.0) / tl.maximum(count, 1).to(px.dtype)
        t = one
        for p0 in range(start, stop, BLOCK):
            offs = p0 + lane
            gid, alpha, visible, dx, dy, ca, cb, cc, falloff, raw = _block_alpha(
                geom_ptr, ids_ptr, offs, stop, px, py, alpha_max, alpha_min
            )
            keep = 1.0 - tl.where(visible, alpha, 0.0)
            if ALPHA_T:
                t_after = t * tl.cumprod(keep, axis=0)
                t_before = t_after / keep
                w = tl.where(visible, alpha * t_before, 0.0)
                g_rows = w[:, None] * g_row[None, :]
            else:
                # every member weighs 1: its row gradient is g_row (row_mask keeps the members). No
                # per-entry weight from ``visible``: Triton 3.6's layout pass (float64, BLOCK 8) breaks
                # a cast or select of it broadcast against the row ("cast incompatible")
                g_rows = tl.zeros([BLOCK, LDP], dtype=px.dtype) + g_row[None, :]
            row_mask = visible[:, None] & value_col[None, :]
            row_ptrs = gid[:, None] * LD1 + cols[None, :]
            tl.atomic_add(g_table_ptr + row_ptrs, g_rows, mask=row_mask, sem="relaxed")
            depth_mask = visible[:, None] & lvl_ok[None, :]
            depth_ptrs = gid[:, None] * LD1 + lvl[None, :] * D1 + (D1 - 1)
            if DIST == 2:
                depth = tl.load(table_ptr + depth_ptrs, mask=depth_mask, other=0.0)
                g_depth = 2.0 * (depth - mean[None, :]) * g_spread[None, :]
                tl.atomic_add(g_table_ptr + depth_ptrs, g_depth, mask=depth_mask, sem="relaxed")
            if DIST == 1:
                signs = tl.zeros([BLOCK, LP], dtype=px.dtype)
                for q0 in range(start, stop, BLOCK):
                    offs_j = q0 + lane
                    gid_j, _al2, vis_j, _dx2, _dy2, _a2, _b2, _c2, _f2, _r2 = _block_alpha(
                        geom_ptr, ids_ptr, offs_j, stop, px, py, alpha_max, alpha_min
                    )
                    for level in range(LEVELS):
                        z_i = tl.load(table_ptr + gid * LD1 + level * D1 + (D1 - 1), mask=visible, other=0.0)
                        z_j = tl.load(table_ptr + gid_j * LD1 + level * D1 + (D1 - 1), mask=vis_j, other=0.0)
                        gap = z_i[:, None] - z_j[None, :]
                        sign = tl.where(gap > 0.0, 1.0, tl.where(gap < 0.0, -1.0, 0.0))
                        sign = tl.where(visible[:, None] & vis_j[None, :], sign, 0.0)
                        signs += tl.where(lvl[None, :] == level, tl.sum(sign, axis=1)[:, None], 0.0)  # pyright: ignore[reportArgumentType]  (triton tensor indexing)
                tl.atomic_add(g_table_ptr + depth_ptrs, signs * g_spread[None, :], mask=depth_mask, sem="relaxed")
            if ALPHA_T:
                t = tl.min(t_after, axis=0)

        if GEOMETRY_GRAD:
            # Back to front, as gsplat's backward: the transmittance in front of each block from the one
            # behind it (t is now T after the last member), and the sum over later members of g_w * w
            # as a suffix sum, so an alpha near alpha_max (1 - alpha small, divided by below) gets no
            # rounding from the members in front of it.
            t_end = t
            behind_block = one * 0.0
            blocks = (stop - start + BLOCK - 1) // BLOCK
            for k in range(0, blocks):
                offs = start + (blocks - 1 - k) * BLOCK + lane
                gid, alpha, visible, dx, dy, ca, cb, cc, falloff, raw = _block_alpha(
                    geom_ptr, ids_ptr, offs, stop, px, py, alpha_max, alpha_min
                )
                keep = 1.0 - tl.where(visible, alpha, 0.0)
                running = tl.cumprod(keep, axis=0)
                t_start = t_end / tl.min(running, axis=0)  # pyright: ignore[reportOperatorIssue]  (triton tensors)
                t_before = t_start * running / keep
                w = tl.where(visible, alpha * t_before, 0.0)
                row_mask = visible[:, None] & value_col[None, :]
                rows = tl.load(table_ptr + gid[:, None] * LD1 + cols[None, :], mask=row_mask, other=0.0)
                g_w = g_wsum + tl.sum(rows * g_row[None, :], axis=1)
                contribution = tl.where(visible, g_w * w, 0.0)
                behind = behind_block + (tl.cumsum(contribution, axis=0, reverse=True) - contribution)
                g_alpha = tl.where(visible, g_w * t_before - behind / keep, 0.0)
                # alpha = min(opacity * exp(-max(sigma, 0)), alpha_max); members have sigma >= 0
                g_raw = tl.where(raw <= alpha_max, g_alpha, 0.0)
                g_opacity = g_raw * falloff
                g_sigma = -g_raw * raw
                base = gid * 6
                tl.atomic_add(g_geom_ptr + base, g_sigma * (ca * dx + cb * dy), mask=visible, sem="relaxed")
                tl.atomic_add(g_geom_ptr + base + 1, g_sigma * (cc * dy + cb * dx), mask=visible, sem="relaxed")
                tl.atomic_add(g_geom_ptr + base + 2, g_sigma * 0.5 * dx * dx, mask=visible, sem="relaxed")
                tl.atomic_add(g_geom_ptr + base + 3, g_sigma * dx * dy, mask=visible, sem="relaxed")
                tl.atomic_add(g_geom_ptr + base + 4, g_sigma * 0.5 * dy * dy, mask=visible, sem="relaxed")
                tl.atomic_add(g_geom_ptr + base + 5, g_opacity, mask=visible, sem="relaxed")
                behind_block += tl.sum(contribution, axis=0)
                t_end = t_start
