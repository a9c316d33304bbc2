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
  With a distortion, the walk also writes each member's id, compacted (slot = rank in
  M), to a per-pixel scratch row of ``member_slots`` slots (as many as a voting set can have members,
  unless that would take too much memory: then ``CAP``); the depth spread, sum_{i<j} |z_i - z_j|
  ("l1", "l1_pixels") or sum_i (z_i - mean)^2 ("squared"), is then summed over those
  slots only, in [PAIR_BLOCK, PAIR_BLOCK] tiles, the depths computed again from the ids
  (``_entry_depths``, the walk's own computation, so the same bits; a row of depths per level
  would take levels x the memory of the id row): |M| ~ 30-70 members instead of the pairs of
  every run entry up to the last member (most of which are not members) with their geometry
  gathered again for each pair of blocks. A pixel with more
  members than its row holds takes that exact slow path: every visible entry up to the last member
  is a member (the transmittance only falls), so pairs of run blocks with the visibility
  recomputed give the same sums.
* backward: re-walks [run start, last member] and scatters, with atomic adds, the gradient
  of every member's table row (weight x row gradient, plus the depth term: sum_j
  sign(z_i - z_j) over the compacted members' depths, or 2 (z_i - mean); with ties in z the
  sign sum gives each tied member the same subgradient, where the torch path's sort splits
  the tie unevenly: the sums over a tie agree) and, for alpha*T weights with geometry gradients, of
  its means2d, conic and opacity: a second walk, back to front as gsplat's backward, carries
  the suffix sum of g_w * w over later members, through which their transmittance depends
  on this alpha.

The jit helpers (the alpha of a run entry, a block of the walk, the member depths, the spread and
the sign sums with their past-``CAP`` paths) also serve :mod:`votesplat_ns.core.vote_fused`'s
kernels: the geometry comes packed [N, 6] here and as separate tensors there, the depths from the
vote table here and from the world votes and ``viewmat`` there. Both clamp ids into [0, N).

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
import math
import os
from typing import Optional, Tuple

import torch
from torch import Tensor

from votesplat_ns.core import triton_launch

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
# Member ids kept per pixel (compacted) for the distortion, and the side of the tiles their depths' pairs are
# summed in. |M| is ~35 on average and ~70 at most on the benchmark scenes; a pixel with more members is
# exact too, on a slower path (module docstring).
CAP = 128
PAIR_BLOCK = 32
# Scratch a call may take to give every pixel a row as long as a voting set can be (member_slots); past it, rows
# keep CAP slots and longer voting sets take the slow exact path, whose pair sums re-walk the run once for each of
# its blocks (a captured training step of a densified scene: 395 ms with 1.3% of its pixels on it, 1.2 ms
# without; BENCHMARKS.md, "Fused vote kernels").
MEMBER_SLOT_BYTES = 256 * 2**20
_DIST_MODES = {"none": 0, "l1": 1, "l1_pixels": 1, "squared": 2}


def member_bound(threshold: float, alpha_min: float, colour_stop: float) -> int:
    """The most members a voting set can have at the voting threshold ``threshold``.

    A member's alpha is at least ``alpha_min``, the transmittance in front of it is above the threshold and the one
    behind it above ``colour_stop``, so after k members it is at most (1 - alpha_min)^k, which must stay above
    max(threshold, colour_stop). The 1e-3 slack covers the float rounding of the walk's running product (~6e-8
    per factor in float32). With vote_render's ALPHA_MIN and COLOUR_STOP_T: 1174 at the default threshold 0.01,
    2346 with none."""
    floor = max(float(threshold), float(colour_stop)) / (1.0 + 1e-3)
    return int(math.log(floor) / math.log1p(-float(alpha_min))) + 2


def member_slots(threshold: float, alpha_min: float, colour_stop: float, pixels: int) -> int:
    """Slots per pixel of a walk's scratch rows (a slot holds a member's int32 id: the distortion computes the
    members' depths again from the ids): ``member_bound`` rounded up to a whole number of pair tiles, so that no
    voting set takes the slow path, unless ``pixels`` such rows would take more than MEMBER_SLOT_BYTES; then CAP."""
    slots = -(-member_bound(threshold, alpha_min, colour_stop) // PAIR_BLOCK) * PAIR_BLOCK
    return CAP if pixels * slots * 4 > MEMBER_SLOT_BYTES else slots


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
    dist = _DIST_MODES[distortion]
    # rows of member ids, only with a distortion
    slots = member_slots(threshold, alpha_min, colour_stop, pixel_xy.shape[0])
    config = (levels, width, bool(alpha_t), dist, slots if dist else CAP)
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
    """Triton launches on the current CUDA device: make it the tensors' one (a switch of devices only where they
    differ: entering and leaving torch.cuda.device costs a training step's vote work two calls a launch)."""
    if device.type != "cuda" or device.index is None or device.index == torch.cuda.current_device():
        return contextlib.nullcontext()
    return torch.cuda.device(device)


def _launch(kernel, grid, *args, **kwargs) -> None:
    """One kernel launch: every launch of the vote kernels goes through here, so it can be counted; on CUDA
    without the JIT's per-call dispatch once the kernel is compiled (``triton_launch``)."""
    triton_launch.launch(kernel, grid, *args, **kwargs)


def _walk_options(cap: int) -> dict:
    """The launch options the walking kernels share: walk width, scratch slots, pair tile side, warps."""
    return {"BLOCK": BLOCK, "CAP": cap, "PB": PAIR_BLOCK, "num_warps": NUM_WARPS}


def _pow2(x: int) -> int:
    return 1 << max(0, (int(x) - 1).bit_length())


class _VoteSums(torch.autograd.Function):
    @staticmethod
    def forward(ctx, geometry, table, pixel_xy, run_start, run_end, flatten_ids, consts, config):
        levels, width, alpha_t, dist, cap = config
        p = pixel_xy.shape[0]
        device, dtype = table.device, table.dtype
        count = torch.empty(p, dtype=torch.int32, device=device)
        last = torch.empty(p, dtype=torch.int64, device=device)
        weight_sum = torch.empty(p, dtype=dtype, device=device)
        value_sum = torch.empty(p, levels * width, dtype=dtype, device=device)
        depth_sum = torch.empty(p, levels, dtype=dtype, device=device)
        spread = torch.empty(p, levels, dtype=dtype, device=device)
        # member ids, compacted: [P, cap] (a dummy pointer without a distortion)
        members = torch.empty(p, cap, dtype=torch.int32, device=device) if dist else count
        if p > 0:
            with _on(device):
                _launch(
                    _vote_fwd_kernel,
                    (p,),
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
                    members,
                    geometry.shape[0],
                    LEVELS=levels,
                    LP=_pow2(levels),
                    D1=width,
                    LDP=_pow2(levels * width),
                    ALPHA_T=alpha_t,
                    DIST=dist,
                    **_walk_options(cap),
                )
        ctx.save_for_backward(
            geometry, table, pixel_xy, run_start, flatten_ids, consts, count, last, depth_sum, members
        )
        ctx.config = config
        ctx.mark_non_differentiable(count, depth_sum)
        return count, weight_sum, value_sum, depth_sum, spread

    @staticmethod
    def backward(ctx, _g_count, g_weight_sum, g_value_sum, _g_depth_sum, g_spread):
        geometry, table, pixel_xy, run_start, flatten_ids, consts, count, last, depth_sum, members = ctx.saved_tensors
        levels, width, alpha_t, dist, cap = ctx.config
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
            _launch(
                _vote_bwd_kernel,
                (p,),
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
                members,
                geometry.shape[0],
                LEVELS=levels,
                LP=_pow2(levels),
                D1=width,
                LDP=_pow2(levels * width),
                ALPHA_T=alpha_t,
                DIST=dist,
                GEOMETRY_GRAD=geometry_grad,
                **_walk_options(cap),
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
    def _program_pixel(pix_ptr, consts_ptr):
        """This program's pixel: its index, ``pix`` = (px, py, alpha_max, alpha_min) as ``_entry_alpha``
        takes it, and ``walk`` = (threshold, open_above, colour_stop) (``_constants``' order)."""
        pid = tl.program_id(0).to(tl.int64)
        pix = (
            tl.load(pix_ptr + 2 * pid),
            tl.load(pix_ptr + 2 * pid + 1),
            tl.load(consts_ptr + 1),
            tl.load(consts_ptr + 3),
        )
        return pid, pix, (tl.load(consts_ptr), tl.load(consts_ptr + 2), tl.load(consts_ptr + 4))

    @triton.jit
    def _entry_alpha(geo, PACKED: tl.constexpr, offs, stop, pix):
        """gsplat's alpha at the pixel ``pix`` for run entries ``offs`` (those >= stop are out), and visibility.

        ``geo`` = (means2d, conics, opacities, flatten_ids, N) pointers and N, ids clamped into [0, N): with
        PACKED the three point into the geometry table [N, 6] (mx, my, a, b, c, opacity) at columns 0, 2 and 5,
        else to separate [N, 2], [N, 3], [N] tensors. Returns gid, alpha, visible and, for the geometry's
        gradient, dx, dy, the conic (a, b, c), exp(-sigma) and the unclamped alpha."""
        means_ptr, conics_ptr, opac_ptr, ids_ptr, n_gauss = geo
        px, py, alpha_max, alpha_min = pix
        M_STRIDE: tl.constexpr = 6 if PACKED else 2
        C_STRIDE: tl.constexpr = 6 if PACKED else 3
        O_STRIDE: tl.constexpr = 6 if PACKED else 1
        inside = offs < stop
        gid = tl.load(ids_ptr + offs, mask=inside, other=0).to(tl.int64)
        gid = tl.minimum(tl.maximum(gid, 0), n_gauss - 1)
        mx = tl.load(means_ptr + M_STRIDE * gid, mask=inside, other=0.0)
        my = tl.load(means_ptr + M_STRIDE * gid + 1, mask=inside, other=0.0)
        ca = tl.load(conics_ptr + C_STRIDE * gid, mask=inside, other=0.0)
        cb = tl.load(conics_ptr + C_STRIDE * gid + 1, mask=inside, other=0.0)
        cc = tl.load(conics_ptr + C_STRIDE * gid + 2, mask=inside, other=0.0)
        opacity = tl.load(opac_ptr + O_STRIDE * gid, mask=inside, other=0.0)
        dx = mx - px
        dy = my - py
        # the operation order of vote_render._alpha, with explicit fmas (as _entry_depths): every copy of this
        # block (the walk, the re-walks, each layout the compiler puts it in) must find the same members, and
        # the compiler may contract mul + add differently per copy. The order is the one it chose before;
        # the interpreter rounds each step: cb * dx * dy + 0.5 * (dx * dx * ca + dy * dy * cc).
        sigma = tl.fma(cb * dx, dy, 0.5 * tl.fma(dx * dx, ca, dy * dy * cc))
        falloff = tl.exp(-tl.maximum(sigma, 0.0))
        raw = opacity * falloff
        alpha = tl.minimum(raw, alpha_max)
        visible = inside & (sigma >= 0.0) & (alpha >= alpha_min)
        return gid, alpha, visible, dx, dy, ca, cb, cc, falloff, raw

    @triton.jit
    def _transmittance(t, alpha, visible):
        """1 - alpha of a block's entries (1 where not visible), and the transmittance behind and in front of
        each, from the transmittance ``t`` in front of the block (module docstring: exact to an ulp)."""
        keep = 1.0 - tl.where(visible, alpha, 0.0)
        t_after = t * tl.cumprod(keep, axis=0)
        return keep, t_after, t_after / keep

    @triton.jit
    def _walk_block(geo, PACKED: tl.constexpr, pos, end, pix, walk, t, last, BLOCK: tl.constexpr):
        """The block of the front-to-back walk at run position ``pos`` (``walk`` from ``_program_pixel``;
        ``t``: the transmittance in front of the block, ``last``: the last member's position before it): the
        entries' gid, alpha, membership in M and transmittance in front of them; the transmittance behind the
        block, the last member's position, the next block's position, and whether to walk on (the run goes on
        and a later entry can still join M)."""
        threshold, open_above, colour_stop = walk
        offs = pos + tl.arange(0, BLOCK).to(tl.int64)
        gid, alpha, visible, _dx, _dy, _a, _b, _c, _f, _r = _entry_alpha(geo, PACKED, offs, end, pix)
        _keep, t_after, t_before = _transmittance(t, alpha, visible)
        member = visible & (t_after > colour_stop) & (t_before > threshold)
        last = tl.maximum(last, tl.max(tl.where(member, offs, -1), axis=0))
        t = tl.min(t_after, axis=0)
        pos += BLOCK
        return gid, alpha, member, t_before, t, last, pos, (pos < end) & (t > open_above)

    @triton.jit
    def _entry_depths(zsrc, PROJECT: tl.constexpr, D1: tl.constexpr, gid, ok, lvl, LEVELS: tl.constexpr):
        """[B, LP] camera depths of every level's vote of Gaussians ``gid`` (0 where not ``ok``), and its x, y, z.

        ``zsrc`` = (vote table [N, LEVELS, D1],): the depth is a row's last column (x, y, z: the depth too);
        with PROJECT, (world votes [N, LEVELS, 3], r0, r1, r2, t2): viewmat's row 2 takes them to the camera;
        PROJECT 2: (offsets [N, LEVELS, 3], r0, r1, r2, t2, means [N, 3]), the votes are means + offsets (the
        float32 sum torch's ``means[:, None] + offsets`` makes, so the same bits)."""
        mask = ok[:, None] & (lvl < LEVELS)[None, :]
        at = zsrc[0] + gid[:, None] * (LEVELS * D1) + lvl[None, :] * D1
        if PROJECT:
            x = tl.load(at, mask=mask, other=0.0)
            y = tl.load(at + 1, mask=mask, other=0.0)
            z = tl.load(at + 2, mask=mask, other=0.0)
            if PROJECT == 2:
                mean_at = zsrc[5] + gid * 3
                x = tl.where(mask, x + tl.load(mean_at, mask=ok, other=0.0)[:, None], 0.0)
                y = tl.where(mask, y + tl.load(mean_at + 1, mask=ok, other=0.0)[:, None], 0.0)
                z = tl.where(mask, z + tl.load(mean_at + 2, mask=ok, other=0.0)[:, None], 0.0)
            # Explicit fmas, no mul + add left for the compiler to contract: it contracts per element, and on
            # sm_90 it fused y * r1 in some lanes of a block and x * r0 in others (the lanes of one layout), so
            # two computations of one depth differed in the last bit and the sign sums past CAP got
            # sign(z_i - z_i) = +-1 for a member against itself and split tied votes. This is the order the
            # compiler chose everywhere in the kernels before these helpers were shared: y * r1 rounded, then
            # x * r0 and z * r2 fused. The interpreter rounds each step: x * r0 + y * r1 + z * r2 + t2, as before.
            depth = tl.where(mask, tl.fma(z, zsrc[3], tl.fma(x, zsrc[1], y * zsrc[2])) + zsrc[4], 0.0)
        else:
            depth = tl.load(at + (D1 - 1), mask=mask, other=0.0)
            x = depth
            y = depth
            z = depth
        return depth, x, y, z

    @triton.jit
    def _sign(x):
        """sign(x), 0 at 0 as torch's."""
        return tl.where(x > 0.0, 1.0, tl.where(x < 0.0, -1.0, 0.0))

    @triton.jit
    def _compact(member, count):
        """Slots ``count`` (|M| before the block) + rank in the block of one walk block's members in the pixel's
        scratch row, and |M| after the block. The caller stores the members' ids at their slots below CAP (those
        past it are dropped: the readers know from |M|); their depths are computed again from the ids."""
        slot = count + tl.cumsum(member.to(tl.int32), axis=0) - 1
        return slot, count + tl.sum(member.to(tl.int32), axis=0)

    @triton.jit
    def _member_spread(
        member_row_ptr,
        m,
        mean,
        runs,
        lvl,
        LEVELS: tl.constexpr,
        PACKED: tl.constexpr,
        PROJECT: tl.constexpr,
        D1: tl.constexpr,
        DIST: tl.constexpr,
        BLOCK: tl.constexpr,
        CAP: tl.constexpr,
        PB: tl.constexpr,
    ):
        """[LP] spread of the m members' depths of each level: sum_{i<j} |z_i - z_j| (DIST 1) or
        sum_i (z_i - mean)^2 (DIST 2), 0 without a distortion. ``runs`` = (geo, pix, zsrc, start, stop) for
        ``_entry_alpha`` / ``_entry_depths``. Up to CAP members: over the compacted member row (``_compact``), in
        [PB, PB] tiles, the depths computed from the ids as the walk computed them (``_entry_depths``: the same
        bits). Past CAP: M is the visible entries of the run [start, last member] (the transmittance only falls),
        by pairs of run blocks."""
        spread = tl.zeros([lvl.shape[0]], dtype=mean.dtype)
        lvl_ok = lvl < LEVELS
        if DIST != 0:
            geo, pix, zsrc, start, stop = runs
            # the members' ids were written by other threads of this program
            tl.debug_barrier()
            if m <= CAP:
                spread = mean * 0.0
                r = tl.arange(0, PB)
                for i0 in range(0, m, PB):
                    ri = i0 + r
                    ok_i = ri < m
                    gid_i = tl.load(member_row_ptr + ri, mask=ok_i, other=0).to(tl.int64)
                    z_i, _x, _y, _z = _entry_depths(zsrc, PROJECT, D1, gid_i, ok_i, lvl, LEVELS)
                    if DIST == 2:
                        deviation = tl.where(ok_i[:, None] & lvl_ok[None, :], z_i - mean[None, :], 0.0)
                        spread += tl.sum(deviation * deviation, axis=0)
                    if DIST == 1:
                        # per level, the sum over the j tiles in order, then added to the spread
                        totals = mean * 0.0
                        for j0 in range(i0, m, PB):
                            rj = j0 + r
                            ok_j = rj < m
                            gid_j = tl.load(member_row_ptr + rj, mask=ok_j, other=0).to(tl.int64)
                            z_j, _x2, _y2, _z2 = _entry_depths(zsrc, PROJECT, D1, gid_j, ok_j, lvl, LEVELS)
                            pair = ok_j[None, :] & (ri[:, None] < rj[None, :])
                            for level in range(LEVELS):
                                zi = tl.sum(tl.where(lvl[None, :] == level, z_i, 0.0), axis=1)
                                zj = tl.sum(tl.where(lvl[None, :] == level, z_j, 0.0), axis=1)
                                gap = tl.where(pair, tl.abs(zi[:, None] - zj[None, :]), 0.0)  # pyright: ignore[reportArgumentType]  (triton tensor indexing)
                                totals += tl.where(lvl == level, tl.sum(tl.sum(gap, axis=1), axis=0), 0.0)
                        spread += totals
            else:
                lane = tl.arange(0, BLOCK).to(tl.int64)
                for p0 in range(start, stop, BLOCK):
                    offs_i = p0 + lane
                    gid_i, _a, vis_i, _dx, _dy, _ca, _cb, _cc, _f, _r = _entry_alpha(geo, PACKED, offs_i, stop, pix)
                    z_i, _x, _y, _z = _entry_depths(zsrc, PROJECT, D1, gid_i, vis_i, lvl, LEVELS)
                    if DIST == 2:
                        deviation = tl.where(vis_i[:, None] & lvl_ok[None, :], z_i - mean[None, :], 0.0)
                        spread += tl.sum(deviation * deviation, axis=0)
                    if DIST == 1:
                        for q0 in range(p0, stop, BLOCK):
                            offs_j = q0 + lane
                            gid_j, _a2, vis_j, _dx2, _dy2, _ca2, _cb2, _cc2, _f2, _r2 = _entry_alpha(
                                geo, PACKED, offs_j, stop, pix
                            )
                            z_j, _x2, _y2, _z2 = _entry_depths(zsrc, PROJECT, D1, gid_j, vis_j, lvl, LEVELS)
                            pair = vis_i[:, None] & vis_j[None, :] & (offs_i[:, None] < offs_j[None, :])
                            for level in range(LEVELS):
                                zi = tl.sum(tl.where(lvl[None, :] == level, z_i, 0.0), axis=1)
                                zj = tl.sum(tl.where(lvl[None, :] == level, z_j, 0.0), axis=1)
                                gap = tl.abs(zi[:, None] - zj[None, :])  # pyright: ignore[reportArgumentType]  (triton tensor indexing)
                                total = tl.sum(tl.sum(tl.where(pair, gap, 0.0), axis=1), axis=0)
                                spread += tl.where(lvl == level, total, 0.0)
        return spread

    @triton.jit
    def _add_tile_signs(signs, z_i, z_j, ok_j, lvl, LEVELS: tl.constexpr):
        """``signs`` [B, LP] plus, per level, sum_j sign(z_i - z_j) over one tile's entries j where ``ok_j`` (z_i
        [B, LP], z_j [B2, LP]): each level's column taken out as a row, its [B, B2] sign tile summed over j."""
        for level in range(LEVELS):
            zi = tl.sum(tl.where(lvl[None, :] == level, z_i, 0.0), axis=1)
            zj = tl.sum(tl.where(lvl[None, :] == level, z_j, 0.0), axis=1)
            sign = _sign(zi[:, None] - zj[None, :])  # pyright: ignore[reportArgumentType]  (triton tensor indexing)
            sign = tl.where(ok_j[None, :], sign, 0.0)
            signs += tl.where(lvl[None, :] == level, tl.sum(sign, axis=1)[:, None], 0.0)  # pyright: ignore[reportArgumentType]  (triton tensor indexing)
        return signs

    @triton.jit
    def _compact_signs(
        z_i,
        member_row_ptr,
        m,
        zsrc,
        lvl,
        LEVELS: tl.constexpr,
        PROJECT: tl.constexpr,
        D1: tl.constexpr,
        PB: tl.constexpr,
    ):
        """[B, LP]: sum_j sign(z_i - z_j) over the m (<= CAP) compacted members, for entries of depths ``z_i``
        [B, LP]; the members' depths computed from their ids in the member row as the walk computed them
        (``_entry_depths`` on ``zsrc``: the same bits, so a member's sign against itself is 0). Rows of entries
        that are not members get a sum too: the callers' scatters mask them."""
        signs = tl.zeros([z_i.shape[0], lvl.shape[0]], dtype=z_i.dtype)
        r = tl.arange(0, PB)
        for j0 in range(0, m, PB):
            rj = j0 + r
            ok_j = rj < m
            gid_j = tl.load(member_row_ptr + rj, mask=ok_j, other=0).to(tl.int64)
            z_j, _x, _y, _z = _entry_depths(zsrc, PROJECT, D1, gid_j, ok_j, lvl, LEVELS)
            signs = _add_tile_signs(signs, z_i, z_j, ok_j, lvl, LEVELS)
        return signs

    @triton.jit
    def _run_signs(
        z_i,
        runs,
        lvl,
        LEVELS: tl.constexpr,
        PACKED: tl.constexpr,
        PROJECT: tl.constexpr,
        D1: tl.constexpr,
        BLOCK: tl.constexpr,
    ):
        """``_compact_signs`` past CAP members, for entries of depths ``z_i`` [B, LP]: the members are the visible
        entries of the run (``runs`` = (geo, pix, zsrc, start, stop) as in ``_member_spread``).

        Rows of entries that are not members get a sum too: the callers' scatters mask them. No mask of the rows
        here: on sm_90 one moved the entries' alpha and depths into the [B, B] sign tile's layout (several
        lanes per value, computed again there) instead of converting the row sums, as the kernels did before
        these helpers were shared."""
        geo, pix, zsrc, start, stop = runs
        signs = tl.zeros([z_i.shape[0], lvl.shape[0]], dtype=z_i.dtype)
        lane = tl.arange(0, BLOCK).to(tl.int64)
        for q0 in range(start, stop, BLOCK):
            offs_j = q0 + lane
            gid_j, _a, vis_j, _dx, _dy, _ca, _cb, _cc, _f, _r = _entry_alpha(geo, PACKED, offs_j, stop, pix)
            z_j, _x, _y, _z = _entry_depths(zsrc, PROJECT, D1, gid_j, vis_j, lvl, LEVELS)
            signs = _add_tile_signs(signs, z_i, z_j, vis_j, lvl, LEVELS)
        return signs

    # n_gauss changes as the scene densifies and only clamps ids: not specialised on (Triton would compile a
    # variant for each new divisibility by 16), as vote_fused's per-step integers
    @triton.jit(do_not_specialize=("n_gauss",))
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
        members_ptr,
        n_gauss,
        LEVELS: tl.constexpr,
        LP: tl.constexpr,
        D1: tl.constexpr,
        LDP: tl.constexpr,
        ALPHA_T: tl.constexpr,
        DIST: tl.constexpr,
        BLOCK: tl.constexpr,
        CAP: tl.constexpr,
        PB: tl.constexpr,
    ):
        pid, pix, walk = _program_pixel(pix_ptr, consts_ptr)
        px = pix[0]
        start = tl.load(start_ptr + pid).to(tl.int64)
        end = tl.load(end_ptr + pid).to(tl.int64)
        geo = (geom_ptr, geom_ptr + 2, geom_ptr + 5, ids_ptr, n_gauss)
        LD1: tl.constexpr = LEVELS * D1
        lane = tl.arange(0, BLOCK).to(tl.int64)
        cols = tl.arange(0, LDP)
        col_ok = cols < LD1
        lvl = tl.arange(0, LP)
        lvl_ok = lvl < LEVELS
        member_row = members_ptr + pid * CAP

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
            gid, alpha, member, t_before, t, last, pos, walking = _walk_block(
                geo, True, pos, end, pix, walk, t, last, BLOCK
            )
            if ALPHA_T:
                w = tl.where(member, alpha * t_before, 0.0)
            else:
                w = member.to(px.dtype)
            wsum += tl.sum(w, axis=0)
            rows = tl.load(
                table_ptr + gid[:, None] * LD1 + cols[None, :], mask=member[:, None] & col_ok[None, :], other=0.0
            )
            vacc += tl.sum(w[:, None] * rows, axis=0)
            depth, _x, _y, _z = _entry_depths((table_ptr,), False, D1, gid, member, lvl, LEVELS)
            zacc += tl.sum(depth, axis=0)
            slot, count = _compact(member, count)
            if DIST != 0:
                tl.store(member_row + slot, gid.to(tl.int32), mask=member & (slot < CAP))

        mean = zacc / tl.maximum(count, 1).to(px.dtype)
        runs = (geo, pix, (table_ptr,), start, last + 1)
        spread = _member_spread(member_row, count, mean, runs, lvl, LEVELS, True, False, D1, DIST, BLOCK, CAP, PB)
        tl.store(count_ptr + pid, count)
        tl.store(last_ptr + pid, last)
        tl.store(wsum_ptr + pid, wsum)
        tl.store(vsum_ptr + pid * LD1 + cols, vacc, mask=col_ok)
        tl.store(zsum_ptr + pid * LEVELS + lvl, zacc, mask=lvl_ok)
        tl.store(spread_ptr + pid * LEVELS + lvl, spread, mask=lvl_ok)

    @triton.jit(do_not_specialize=("n_gauss",))
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
        members_ptr,
        n_gauss,
        LEVELS: tl.constexpr,
        LP: tl.constexpr,
        D1: tl.constexpr,
        LDP: tl.constexpr,
        ALPHA_T: tl.constexpr,
        DIST: tl.constexpr,
        GEOMETRY_GRAD: tl.constexpr,
        BLOCK: tl.constexpr,
        CAP: tl.constexpr,
        PB: tl.constexpr,
    ):
        pid, pix, _walk = _program_pixel(pix_ptr, consts_ptr)
        px = pix[0]
        alpha_max = pix[2]
        start = tl.load(start_ptr + pid).to(tl.int64)
        stop = tl.load(last_ptr + pid) + 1
        count = tl.load(count_ptr + pid)
        geo = (geom_ptr, geom_ptr + 2, geom_ptr + 5, ids_ptr, n_gauss)
        runs = (geo, pix, (table_ptr,), start, stop)
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
            gid, alpha, visible, _dx, _dy, _a, _b, _c, _f, _r = _entry_alpha(geo, True, offs, stop, pix)
            if ALPHA_T:
                _keep, t_after, t_before = _transmittance(t, alpha, visible)
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
                depth, _x, _y, _z = _entry_depths((table_ptr,), False, D1, gid, visible, lvl, LEVELS)
                g_depth = 2.0 * (depth - mean[None, :]) * g_spread[None, :]
                tl.atomic_add(g_table_ptr + depth_ptrs, g_depth, mask=depth_mask, sem="relaxed")
            if DIST == 1:
                depth, _x, _y, _z = _entry_depths((table_ptr,), False, D1, gid, visible, lvl, LEVELS)
                if count <= CAP:
                    member_row = members_ptr + pid * CAP
                    signs = _compact_signs(depth, member_row, count, (table_ptr,), lvl, LEVELS, False, D1, PB)
                else:
                    signs = _run_signs(depth, runs, lvl, LEVELS, True, False, D1, BLOCK)
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
                gid, alpha, visible, dx, dy, ca, cb, cc, falloff, raw = _entry_alpha(geo, True, offs, stop, pix)
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
