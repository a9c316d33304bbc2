"""The vote walk in Triton: the jit helpers that :mod:`votesplat_ns.core.vote_fused`'s kernels are made of,
their sizes, and the one place the vote kernels launch.

Same membership rule, levels and distortions as :mod:`votesplat_ns.core.vote_render` (read its module
docstring). A kernel program handles one sampled pixel:

* the walk (``_walk_block``, a block at a time) goes through the pixel's tile run front to back in blocks of
  ``BLOCK`` entries, carrying the transmittance across blocks (inclusive ``cumprod`` within a block; the
  transmittance in front of an entry is the inclusive product divided by its own 1 - alpha, exact to an ulp,
  and VOTE_THRESHOLD_RTOL absorbs that ulp at the threshold). It stops once the transmittance is at or below
  both the voting threshold and the colour stop, or the run ends.
* with a distortion, the walk writes each member's id, compacted (slot = rank in M, ``_compact``), to a
  per-pixel scratch row of ``member_slots`` slots (as many as a voting set can have members, unless that
  would take too much memory: then ``CAP``); the depth spread, sum_{i<j} |z_i - z_j| ("l1", "l1_pixels") or
  sum_i (z_i - mean)^2 ("squared"), is then summed over those slots only, in [PAIR_BLOCK, PAIR_BLOCK] tiles
  (``_member_spread``), the depths computed again from the ids (``_entry_depths``, the walk's own
  computation, so the same bits; a row of depths per level would take levels x the memory of the id row). A
  pixel with more members than its row holds takes the exact slow path: every visible entry up to the last
  member is a member (the transmittance only falls), so pairs of run blocks with the visibility recomputed
  give the same sums.
* the backward's depth term is sum_j sign(z_i - z_j) over the compacted members' depths (``_compact_signs``;
  past the row, over the run: ``_run_signs``), or 2 (z_i - mean); with ties in z the sign sum gives each
  tied member the same subgradient, where the torch path's sort splits the tie unevenly: the sums over a tie
  agree.

Ids are clamped into [0, N). Every launch of the vote kernels goes through ``_launch`` (so it can be
counted), through Triton's own ``kernel[grid]``.

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
    """One kernel launch through Triton's ``kernel[grid]``: every launch of the vote kernels goes through here, so
    it can be counted. (Calling the compiled launcher directly saves ~38 us of host time a launch but nothing
    measurable in a whole training: BENCHMARKS.md "Training time".)"""
    kernel[grid](*args, **kwargs)


def _walk_options(cap: int) -> dict:
    """The launch options the walking kernels share: walk width, scratch slots, pair tile side, warps."""
    return {"BLOCK": BLOCK, "CAP": cap, "PB": PAIR_BLOCK, "num_warps": NUM_WARPS}


def _pow2(x: int) -> int:
    return 1 << max(0, (int(x) - 1).bit_length())


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
    def _entry_alpha(geo, offs, stop, pix):
        """gsplat's alpha at the pixel ``pix`` for run entries ``offs`` (those >= stop are out), and visibility.

        ``geo`` = (means2d [N, 2], conics [N, 3], opacities [N], flatten_ids) pointers and N, ids clamped into
        [0, N). Returns gid, alpha, visible and, for the geometry's gradient, dx, dy, the conic (a, b, c),
        exp(-sigma) and the unclamped alpha."""
        means_ptr, conics_ptr, opac_ptr, ids_ptr, n_gauss = geo
        px, py, alpha_max, alpha_min = pix
        inside = offs < stop
        gid = tl.load(ids_ptr + offs, mask=inside, other=0).to(tl.int64)
        gid = tl.minimum(tl.maximum(gid, 0), n_gauss - 1)
        mx = tl.load(means_ptr + 2 * gid, mask=inside, other=0.0)
        my = tl.load(means_ptr + 2 * gid + 1, mask=inside, other=0.0)
        ca = tl.load(conics_ptr + 3 * gid, mask=inside, other=0.0)
        cb = tl.load(conics_ptr + 3 * gid + 1, mask=inside, other=0.0)
        cc = tl.load(conics_ptr + 3 * gid + 2, mask=inside, other=0.0)
        opacity = tl.load(opac_ptr + gid, mask=inside, other=0.0)
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
    def _walk_block(geo, pos, end, pix, walk, t, last, BLOCK: tl.constexpr):
        """The block of the front-to-back walk at run position ``pos`` (``walk`` from ``_program_pixel``;
        ``t``: the transmittance in front of the block, ``last``: the last member's position before it): the
        entries' gid, alpha, membership in M and transmittance in front of them; the transmittance behind the
        block, the last member's position, the next block's position, and whether to walk on (the run goes on
        and a later entry can still join M)."""
        threshold, open_above, colour_stop = walk
        offs = pos + tl.arange(0, BLOCK).to(tl.int64)
        gid, alpha, visible, _dx, _dy, _a, _b, _c, _f, _r = _entry_alpha(geo, offs, end, pix)
        _keep, t_after, t_before = _transmittance(t, alpha, visible)
        member = visible & (t_after > colour_stop) & (t_before > threshold)
        last = tl.maximum(last, tl.max(tl.where(member, offs, -1), axis=0))
        t = tl.min(t_after, axis=0)
        pos += BLOCK
        return gid, alpha, member, t_before, t, last, pos, (pos < end) & (t > open_above)

    @triton.jit
    def _entry_depths(zsrc, PROJECT: tl.constexpr, gid, ok, lvl, LEVELS: tl.constexpr):
        """[B, LP] camera depths of every level's vote of Gaussians ``gid`` (0 where not ``ok``), and its x, y, z.

        ``zsrc``: PROJECT 1, (world votes [N, LEVELS, 3], r0, r1, r2, t2): viewmat's row 2 takes them to the
        camera; PROJECT 2, (offsets [N, LEVELS, 3], r0, r1, r2, t2, means [N, 3]), the votes are means + offsets
        (the float32 sum torch's ``means[:, None] + offsets`` makes, so the same bits)."""
        mask = ok[:, None] & (lvl < LEVELS)[None, :]
        at = zsrc[0] + gid[:, None] * (LEVELS * 3) + lvl[None, :] * 3
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
        PROJECT: tl.constexpr,
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
                    z_i, _x, _y, _z = _entry_depths(zsrc, PROJECT, gid_i, ok_i, lvl, LEVELS)
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
                            z_j, _x2, _y2, _z2 = _entry_depths(zsrc, PROJECT, gid_j, ok_j, lvl, LEVELS)
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
                    gid_i, _a, vis_i, _dx, _dy, _ca, _cb, _cc, _f, _r = _entry_alpha(geo, offs_i, stop, pix)
                    z_i, _x, _y, _z = _entry_depths(zsrc, PROJECT, gid_i, vis_i, lvl, LEVELS)
                    if DIST == 2:
                        deviation = tl.where(vis_i[:, None] & lvl_ok[None, :], z_i - mean[None, :], 0.0)
                        spread += tl.sum(deviation * deviation, axis=0)
                    if DIST == 1:
                        for q0 in range(p0, stop, BLOCK):
                            offs_j = q0 + lane
                            gid_j, _a2, vis_j, _dx2, _dy2, _ca2, _cb2, _cc2, _f2, _r2 = _entry_alpha(
                                geo, offs_j, stop, pix
                            )
                            z_j, _x2, _y2, _z2 = _entry_depths(zsrc, PROJECT, gid_j, vis_j, lvl, LEVELS)
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
            z_j, _x, _y, _z = _entry_depths(zsrc, PROJECT, gid_j, ok_j, lvl, LEVELS)
            signs = _add_tile_signs(signs, z_i, z_j, ok_j, lvl, LEVELS)
        return signs

    @triton.jit
    def _run_signs(
        z_i,
        runs,
        lvl,
        LEVELS: tl.constexpr,
        PROJECT: tl.constexpr,
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
            gid_j, _a, vis_j, _dx, _dy, _ca, _cb, _cc, _f, _r = _entry_alpha(geo, offs_j, stop, pix)
            z_j, _x, _y, _z = _entry_depths(zsrc, PROJECT, gid_j, vis_j, lvl, LEVELS)
            signs = _add_tile_signs(signs, z_i, z_j, vis_j, lvl, LEVELS)
        return signs
