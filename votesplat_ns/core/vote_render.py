"""Vote splatting and its losses (VoteSplat, ICCV 2025, section 3.3).

Each Gaussian i carries a 3D vote V_i = p_i + dp_i (world space). For a pixel,
the Gaussians are walked front to back exactly as gsplat 1.4 alpha-composites
colour, and the *voting set* M is built from that walk. The pixel's 3D vote is
the uniform mean of the votes in M (paper Eq. 8), blended in 3D and only then
projected to the image (Eq. 9); the depth regulariser is the unweighted
pairwise spread of the vote depths in M (Eq. 12).

Membership rule for M (the paper says only "the depth-ordered points under the voting
transmittance"; this is the rule the implementation reads it as):
    A Gaussian that the colour pass composites (sigma >= 0, alpha >= 1/255,
    and it does not end the colour walk by bringing T to <= 1e-4) joins M
    when the transmittance in front of it, T_i, is above the voting threshold
    ``vote_transmittance`` (default 0.01). The walk therefore stops after the
    Gaussian that brings the transmittance to or below the threshold, and that
    Gaussian is the last member.
    Why "in front of" and not "after": alpha is clamped to ``alpha_max``
    (0.99), so with "T after it > 0.01" a lone opaque Gaussian would leave M
    empty.
    ``vote_transmittance = 0`` removes the cut-off: M is then every Gaussian
    the colour pass composites (the paper's "no voting transmittance"
    ablation).
    Transmittances within a relative ``VOTE_THRESHOLD_RTOL`` of the threshold
    count as having reached it, so that 1 - 0.99, which equals the default
    threshold in exact arithmetic, ends M in float32 and float64 alike.

Mask levels: VoteSplat trains one offset per Gaussian per SAM mask level, so
``votes`` may be [N, L, 3] (one vote per level) instead of [N, 3]. The voting
set depends on the geometry only, never on the votes, so it is found once and
every level's votes are blended over it: the outputs gain a level axis after
the pixel axis, ``count`` stays [P], and one call costs little more than a
single level.

Everything here is pure torch (no nerfstudio import) and runs on any device.
Two implementations share the alpha, walk and reduction helpers:

* ``render_votes_reference``: dense [pixels, Gaussians], readable; the CPU
  path for small scenes and the oracle for tests.
* ``render_votes_tiled``: the training path. Walks gsplat's per-tile
  depth-sorted intersection lists in wide steps without autograd to find
  each pixel's voting set, then blends the members' votes with autograd on a
  compact [pixels, max |M|] table. A training step is bound by kernel
  launches and host synchronisations rather than arithmetic, so this path
  reads device values on the host as rarely as it can (see its docstring).
  A training step on CUDA computes the same losses in fused Triton kernels
  instead (``votesplat_ns.core.vote_fused``, chosen by
  ``VoteRenderOptions.backend``); this torch code stays their reference and
  the CPU path.

Conventions (shared by the whole project): OpenCV world-to-camera ``viewmat``
[4,4], intrinsics ``K`` [3,3], continuous pixel frame in which the centre of
pixel column x / row y is (x + 0.5, y + 0.5) (gsplat's).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Dict, NamedTuple, Optional, Tuple

import torch
from torch import Tensor

# gsplat 1.4 compositing constants (rasterize_to_pixels_fwd.cu).
ALPHA_MIN = 1.0 / 255.0
COLOUR_STOP_T = 1e-4
# Relative slack on the voting threshold; see the module docstring.
VOTE_THRESHOLD_RTOL = 1e-5
# Width of a step of the tiled walk when ``chunk`` is None: about this many
# pixel-Gaussian pairs per step, at least AUTO_MIN_CHUNK Gaussians per pixel.
# On a GPU a step costs ~40 kernel launches and a host read; 2M pairs of
# unfused elementwise work is an estimate of what an H100 gets through in that
# launch time (not measured), so most walks take one step. On CPU there is
# nothing to amortise and narrow blocks stay in cache (measured, 100k
# Gaussians, 4096 pixels, one thread: 280 ms fwd+bwd at 32 wide, 330 at 512).
AUTO_PAIRS_PER_STEP = 1 << 21
AUTO_PAIRS_PER_STEP_CPU = 1 << 17
AUTO_MIN_CHUNK = 32

_WEIGHTINGS = ("uniform", "alpha_t")
_BLEND_SPACES = ("3d", "2d")
_DISTORTIONS = ("l1", "l1_pixels", "squared", "none")
_BACKENDS = ("auto", "torch", "triton")
BACKEND_ENV = "VOTESPLAT_VOTE_BACKEND"


@dataclass(frozen=True)
class VoteRenderOptions:
    """Switches for the vote renderer, covering the ablations of Table 3 / Fig. 7.

    weighting: "uniform" (paper Eq. 8: plain mean over M) or "alpha_t"
        (weights alpha_i * T_i over M, normalised by their sum; the
        conventional alpha-blending the paper argues against).
    blend_space: "3d" (average the 3D votes, then project the mean; paper) or
        "2d" (project each vote, then average the 2D points with the same
        weights).
    distortion: "l1" (sum over pairs i<j in M of |z_i - z_j|, Eq. 12),
        "l1_pixels" (the same pairs, scale-free: their mean |z_i - z_j| times
        f / z_mean, i.e. in pixels, the unit of the vote loss: the lateral
        error that a vote displacement of that size would make at the
        members' mean depth z_mean; f = sqrt(fx fy), and f / z_mean is held
        constant in the gradient so moving votes away cannot shrink it),
        "squared" (sum over pairs of (z_i - z_j)^2) or "none". z is the
        camera-space depth of each Gaussian's vote; every form is unweighted
        in every weighting mode. The pair sum of "l1" grows with |M|^2 and
        with the scene's units, so one lambda_d means different things on
        different captures; "l1_pixels" does not.
    vote_transmittance: voting threshold on the transmittance in front of a
        Gaussian; 0 disables the cut-off.
    detach_geometry: True: gradients reach the votes only, never means2d,
        conics, opacities, depths, viewmat or K (geometry is the RGB loss's
        job). False: they also flow to means2d, conics and opacities through
        the alpha_t weights and the transmittance, and to viewmat/K through
        the projection. Note that the renderer only sees V = p + dp: to keep
        the means p out of the vote loss the caller passes
        ``means.detach() + offsets``.
    alpha_max: clamp on a Gaussian's alpha: 0.999, as gsplat 1.4's CUDA
        kernel and our torch rasteriser, so the voting walk sees the same
        alphas as the colour pass.
    vote_near_plane: votes whose camera depth is below this (including votes
        behind the camera) are projected as if at this depth, so projected
        votes stay finite; in scene units, like gsplat's near_plane. The
        depth regulariser uses the unclamped depth.
    backend: how the model's vote step computes its losses
        (``votesplat_ns.core.vote_fused.use_fused``). "auto": on CUDA the
        fused Triton losses (``vote_fused``: render and losses in three
        launches, no host read) where the switches allow (uniform weights, 3D
        blending, detach_geometry), else this module's torch code. "torch":
        always the torch code. "triton": the fused losses where the switches
        allow, also on CPU under Triton's interpreter (TRITON_INTERPRET=1, for
        tests); an error where the kernels cannot run. The environment variable
        VOTESPLAT_VOTE_BACKEND=torch|triton overrides "auto". Values agree to
        rounding, gradients too. ``render_votes_tiled`` and the dense reference
        ignore it.
    """

    weighting: str = "uniform"
    blend_space: str = "3d"
    distortion: str = "l1"
    vote_transmittance: float = 0.01
    detach_geometry: bool = True
    alpha_max: float = 0.999
    vote_near_plane: float = 0.01
    backend: str = "auto"

    def __post_init__(self) -> None:
        if self.weighting not in _WEIGHTINGS:
            raise ValueError(f"VoteRenderOptions.weighting must be one of {_WEIGHTINGS}, got {self.weighting!r}")
        if self.blend_space not in _BLEND_SPACES:
            raise ValueError(f"VoteRenderOptions.blend_space must be one of {_BLEND_SPACES}, got {self.blend_space!r}")
        if self.distortion not in _DISTORTIONS:
            raise ValueError(f"VoteRenderOptions.distortion must be one of {_DISTORTIONS}, got {self.distortion!r}")
        if not 0.0 <= float(self.vote_transmittance) < 1.0:
            raise ValueError(f"VoteRenderOptions.vote_transmittance must be in [0, 1), got {self.vote_transmittance!r}")
        if not ALPHA_MIN < float(self.alpha_max) < 1.0:
            raise ValueError(f"VoteRenderOptions.alpha_max must be in (1/255, 1), got {self.alpha_max!r}")
        if not float(self.vote_near_plane) > 0.0:
            raise ValueError(f"VoteRenderOptions.vote_near_plane must be > 0, got {self.vote_near_plane!r}")
        if self.backend not in _BACKENDS:
            raise ValueError(f"VoteRenderOptions.backend must be one of {_BACKENDS}, got {self.backend!r}")


class VoteRender(NamedTuple):
    """Per-pixel result of vote splatting for P pixels (and L levels for [N, L, 3] votes).

    Pixels with an empty voting set (count == 0) hold zeros in every field;
    mask them with ``count > 0`` (``vote_losses`` does).
    """

    mean_vote: Tensor  # [P, 3] or [P, L, 3]: blended 3D vote, world space
    projected_vote: Tensor  # [P, 2] or [P, L, 2]: in the continuous pixel frame
    count: Tensor  # [P] int64, |M| (shared by the levels)
    distortion: Tensor  # [P] or [P, L]: pairwise vote-depth spread over M (per options.distortion)


def project_to_pixels(points: Tensor, viewmat: Tensor, K: Tensor, near_plane: float = 0.01) -> Tensor:
    """Project world points [..., 3] to the continuous pixel frame [..., 2].

    Depths below ``near_plane`` are clamped to it so the result is finite for
    points behind the camera.
    """
    cam = _to_camera(points, viewmat)
    return _camera_to_pixels(cam, K, near_plane)


def render_votes_reference(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    depths: Tensor,
    votes: Tensor,
    viewmat: Tensor,
    K: Tensor,
    pixel_xy: Tensor,
    options: Optional[VoteRenderOptions] = None,
    pixel_chunk: Optional[int] = None,
) -> VoteRender:
    """Dense vote splatting: every pixel against every Gaussian.

    Args:
        means2d [N,2], conics [N,3], opacities [N], depths [N]: the Gaussians
            projected to one camera, as gsplat computes them. All N are used,
            so they must be finite (drop culled Gaussians first). Ties in
            depth keep the input order.
        votes [N,3] or [N,L,3]: world-space votes p_i + dp_i, optionally one
            per mask level; with a level axis every output but ``count`` gets
            one too.
        viewmat [4,4], K [3,3]: the camera.
        pixel_xy [P,2]: continuous positions to evaluate (pixel centre of
            column x is x + 0.5).
        options: ``VoteRenderOptions`` (defaults to the paper's settings).
        pixel_chunk: pixels per dense block; by default about 4M
            pixel-Gaussian pairs per block.
    """
    options = options or VoteRenderOptions()
    n, p, levels = _validate_inputs(means2d, conics, opacities, depths, votes, viewmat, K, pixel_xy)
    finite = _finiteness_checks(votes, pixel_xy)
    for name, t in (("means2d", means2d), ("conics", conics), ("opacities", opacities), ("depths", depths)):
        finite[
            f"{name} contains NaN or inf; the dense reference uses every Gaussian, so drop culled ones "
            f"(radii == 0) before calling it"
        ] = _all_finite(t)
    _raise_unless(_read_host(finite))
    if n == 0 or p == 0:
        return _empty_render(p, votes, viewmat, K, options)
    if pixel_chunk is None:
        pixel_chunk = max(1, (1 << 22) // (n * levels))
    if pixel_chunk < 1:
        raise ValueError(f"pixel_chunk must be >= 1, got {pixel_chunk}")

    order = torch.argsort(depths.detach(), stable=True)
    geometry = _geometry_table(means2d, conics, opacities, options)[order]
    viewmat_, K_ = _camera(viewmat, K, options)
    vote_table = _vote_table(votes.reshape(n, levels, 3), viewmat_, K_, options)[order]
    blend_values = vote_table[..., :-1].reshape(n, -1)
    vote_z = vote_table[..., -1]
    threshold = _vote_threshold(options)

    parts = []
    for begin in range(0, p, pixel_chunk):
        xy = pixel_xy[begin : begin + pixel_chunk]
        rows = geometry.unsqueeze(0)
        alpha, visible = _alpha(rows[..., 0:2], rows[..., 2:5], rows[..., 5], xy[:, None, :], options.alpha_max)
        t_front = torch.ones(xy.shape[0], dtype=alpha.dtype, device=alpha.device)
        member, t_before, _ = _walk(alpha, visible, t_front, threshold)
        weights = _weights(member, alpha, t_before, options)
        count = member.sum(dim=1)
        value_sum = (weights @ blend_values).view(xy.shape[0], levels, -1)
        z = vote_z.unsqueeze(0).expand(xy.shape[0], n, levels)
        distortion = _distortion(z, member, count, value_sum, options, K_)
        parts.append((count, weights.sum(dim=1), value_sum, distortion))

    count, weight_sum, value_sum, distortion = (torch.cat(x, dim=0) for x in zip(*parts))
    return _finish(count, weight_sum, value_sum, distortion, viewmat_, K_, options, votes.ndim == 2)


def render_votes_tiled(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    depths: Tensor,
    votes: Tensor,
    viewmat: Tensor,
    K: Tensor,
    pixel_xy: Tensor,
    isect_offsets: Tensor,
    flatten_ids: Tensor,
    tile_size: int,
    options: Optional[VoteRenderOptions] = None,
    chunk: Optional[int] = None,
) -> VoteRender:
    """Vote splatting over gsplat 1.4's tile intersection lists (the fast path).

    Args:
        means2d, conics, opacities, depths, votes, viewmat, K, pixel_xy: as in
            ``render_votes_reference`` (``votes`` [N,3] or [N,L,3]).
            ``depths`` is only shape-checked: the order comes from the lists.
            Entries of Gaussians absent from the lists (culled, radii == 0)
            are never read, so they may hold anything.
        isect_offsets [tile_height, tile_width] (or [1, th, tw]) int: start of
            each tile's run in ``flatten_ids`` (gsplat ``isect_offset_encode``
            for ONE camera); the last tile's run ends at len(flatten_ids).
        flatten_ids [n_isects] int: Gaussian ids of each run, front to back
            (gsplat ``isect_tiles`` with C = 1, packed = False, so ids are in
            [0, N)).
        tile_size: pixels per tile side of the grid the lists were built for.
        chunk: Gaussians gathered per pixel per step of the walk. None (the
            default): about ``AUTO_PAIRS_PER_STEP`` pixel-Gaussian pairs per
            step (``AUTO_PAIRS_PER_STEP_CPU`` on CPU), at least
            ``AUTO_MIN_CHUNK``. Never wider than ``flatten_ids`` (the longest
            run is not known before the walk: reading it would cost a host
            synchronisation).

    A pixel at continuous position (x, y) reads tile (floor(x / tile_size),
    floor(y / tile_size)); positions outside the tile grid get count 0.

    Design: two passes.
    1. Membership, without autograd: all pixels advance through their tile's
       run together, one gathered [P, chunk] block per step, carrying the
       transmittance; each step's members are scattered into a [P, capacity]
       table of Gaussian ids (slot = |M| so far + rank within the step). A
       pixel can gain members only while the transmittance in front of it is
       above both the voting threshold and the colour stop and its run has
       entries left, so the walk is exact once the longest run among the
       still-open pixels has been walked.
    2. Blending, with autograd: gather the members' votes (all levels at
       once) [P, max |M|, L, ...] and reduce them; the pairwise L1 depth term
       is exact via the sorted identity sum_k z_(k) (2k - m - 1). The members
       of a pixel are exactly the visible Gaussians of its walk up to the
       last member (transmittance only falls, so none is skipped before it),
       so the transmittance in front of a member is the product of
       (1 - alpha) over the earlier members: the alpha_t weights are
       recomputed there, differentiably when ``detach_geometry`` is False.
    Autograd thus sees a handful of ops on [P, max |M|] however long the
    runs are. Values and gradients match ``render_votes_reference`` whenever
    each tile's run holds every Gaussian whose alpha can reach 1/255 in it.

    Host synchronisations: one per step of the walk: each step's read gives
    the termination test (no open pixel has entries left) and the table width
    max |M|, the first also the input checks (finite votes and pixel_xy, ids
    and offsets in range), so bad inputs still raise before anything is
    returned. With the default ``chunk`` on a GPU a walk usually takes one
    step, so the pass (forward and backward) reads the host once. Until that
    read the walk clamps positions and ids into range, so bad lists cannot
    make it index out of bounds.
    Unused table slots hold real Gaussian ids from the pixel's own run with
    zero weight, so the gathers have fixed shapes (no nonzero) and their
    backward (an atomic index_add) does not pile the padding onto one row.
    """
    options = options or VoteRenderOptions()
    n, p, levels = _validate_inputs(means2d, conics, opacities, depths, votes, viewmat, K, pixel_xy)
    offsets, tiles_high, tiles_wide = _validate_tiles(isect_offsets, flatten_ids, tile_size, chunk, votes.device)
    n_isects = flatten_ids.numel()
    # Device values the input checks need, read with the walk's first host read instead of a read of their own.
    pending = {"finite": _all_finite(votes, pixel_xy)}
    if n_isects > 0:
        pending["ids_low"], pending["ids_high"] = torch.aminmax(flatten_ids)
    if offsets.numel() > 0:
        pending["offsets_low"], pending["offsets_high"] = torch.aminmax(offsets)
    if n == 0 or p == 0 or n_isects == 0 or offsets.numel() == 0:
        _check_render_inputs(_read_host(pending), n, n_isects, votes, pixel_xy)
        return _empty_render(p, votes, viewmat, K, options)
    run_start, run_end = _pixel_runs(pixel_xy.detach(), offsets, tiles_high, tiles_wide, tile_size, n_isects)

    if chunk is None:
        pairs = AUTO_PAIRS_PER_STEP_CPU if votes.device.type == "cpu" else AUTO_PAIRS_PER_STEP
        chunk = max(AUTO_MIN_CHUNK, pairs // p)
    geometry = _geometry_table(means2d, conics, opacities, options)
    threshold = _vote_threshold(options)
    with torch.no_grad():
        # No run is longer than the list: walking up to n_isects entries is exact, and the walk stops at
        # its first read once no open pixel has entries left, so the bound costs no read of its own.
        member_ids, count = _tiled_members(
            geometry.detach(),
            pixel_xy.detach(),
            run_start,
            run_end,
            flatten_ids,
            min(chunk, n_isects),
            n_isects,
            threshold,
            options.alpha_max,
            host=pending,
        )
    _check_render_inputs(pending, n, n_isects, votes, pixel_xy)
    capacity = member_ids.shape[1]
    if capacity == 0:
        return _empty_render(p, votes, viewmat, K, options)
    viewmat_, K_ = _camera(viewmat, K, options)
    vote_table = _vote_table(votes.reshape(n, levels, 3), viewmat_, K_, options)
    # indexed with the [P, max |M|] table itself: a flat index would copy the (strided) table first
    member_votes = vote_table[member_ids]
    filled = torch.arange(capacity, device=count.device) < count[:, None]
    n_members = count.to(votes.dtype)
    if options.weighting == "alpha_t":
        rows = geometry[member_ids]
        alpha, _ = _alpha(rows[..., 0:2], rows[..., 2:5], rows[..., 5], pixel_xy[:, None, :], options.alpha_max)
        alpha = torch.where(filled, alpha, 0.0)
        weights = alpha * _transmittance_in_front(alpha)
        weight_sum = weights.sum(dim=1)
    else:
        weights = filled.to(votes.dtype)
        weight_sum = n_members
    value_sum = (weights[:, :, None, None] * member_votes[..., :-1]).sum(dim=1)
    distortion = _distortion(member_votes[..., -1], filled, count, value_sum, options, K_, n_members, True)
    return _finish(count, weight_sum, value_sum, distortion, viewmat_, K_, options, votes.ndim == 2)


def _check_render_inputs(host: Dict[str, Any], n: int, n_isects: int, votes: Tensor, pixel_xy: Tensor) -> None:
    """Raise the input errors of render_votes_tiled from the host values of its pending checks."""
    if not host["finite"]:
        # which of the two (more reads, on the error path only)
        _raise_unless(_read_host(_finiteness_checks(votes, pixel_xy)))
    if n_isects > 0 and (host["ids_low"] < 0 or host["ids_high"] >= n):
        raise ValueError(
            f"flatten_ids must index the N = {n} Gaussians of one camera, got ids in "
            f"[{host['ids_low']}, {host['ids_high']}]; build the lists with C = 1 and packed = False"
        )
    if "offsets_low" in host and (host["offsets_low"] < 0 or host["offsets_high"] > n_isects):
        raise ValueError("isect_offsets point outside flatten_ids; pass the offsets and ids of the same camera")


def _requested_backend(options: VoteRenderOptions) -> str:
    """options.backend with "auto" resolved through VOTESPLAT_VOTE_BACKEND ("auto" when unset)."""
    backend = options.backend
    if backend == "auto":
        backend = os.environ.get(BACKEND_ENV, "auto") or "auto"
        if backend not in _BACKENDS:
            raise ValueError(f"{BACKEND_ENV} must be one of {_BACKENDS}, got {backend!r}")
    return backend


def _tiled_members(
    geometry: Tensor,
    pixel_xy: Tensor,
    run_start: Tensor,
    run_end: Tensor,
    flatten_ids: Tensor,
    width: int,
    longest: int,
    threshold: float,
    alpha_max: float,
    early_exit: bool = True,
    host: Optional[Dict[str, Any]] = None,
) -> Tuple[Tensor, Tensor]:
    """Voting sets from the tile lists: ([P, max |M|] Gaussian ids, [P] |M|).

    Walks ``width`` entries of every pixel's run per step, at most
    ceil(longest / width) steps (``longest``: a bound on the run lengths).
    With ``early_exit`` the walk stops as soon as no open pixel has entries
    left (one host read per step but the last); without, it always takes
    every step (no read until the end), which gives the same result. Slots
    past a pixel's |M| hold ids from its own run. ``host``: 0-d device values
    to read along with the first host read; their entries are replaced by
    the host values. The lists are not trusted before that read: positions
    and ids are clamped into range, so bad lists give wrong sets, not a crash,
    and the caller raises on the values read.
    """
    p, device = pixel_xy.shape[0], pixel_xy.device
    last_entry = flatten_ids.numel() - 1
    last_id = geometry.shape[0] - 1
    steps = -(-longest // width)
    # Below either transmittance no later Gaussian can join M (T only falls).
    open_above = max(threshold, COLOUR_STOP_T)
    first_position = run_start[:, None] + torch.arange(width, device=device)
    pending = dict(host) if host else {}

    def read(values: Dict[str, Tensor]) -> Dict[str, int]:
        """One host read of ``values``, and of the pending ``host`` values the first time."""
        if not pending:
            return _read_host(values)
        both = _read_host({**{("walk", k): v for k, v in values.items()}, **pending})
        assert host is not None  # pending is a copy of it
        host.update({k: both[k] for k in pending})
        pending.clear()
        return {k: both[("walk", k)] for k in values}

    # table[:, 0] takes the non-members (dropped at the end); table[:, 1 + k] holds member k, or until a
    # member is written there, entry k of the pixel's run (valid filler)
    table = None
    count = t_front = None
    capacity = width
    bound = 0  # an upper bound on max |M|, exact after each read
    walked = False
    for step in range(steps):
        bound += width
        position = first_position if step == 0 else first_position + step * width
        ids = flatten_ids[position.clamp(0, last_entry)].clamp(0, last_id)
        if table is None:
            table = torch.cat([ids[:, :1], ids], dim=1)
        elif bound > capacity:
            grown = max(bound, 2 * capacity)
            table = torch.cat([table, _run_entries(run_start, flatten_ids, capacity, grown)], dim=1)
            capacity = grown
        rows = geometry.index_select(0, ids.view(-1)).view(p, width, -1)
        alpha, visible = _alpha(rows[..., 0:2], rows[..., 2:5], rows[..., 5], pixel_xy[:, None, :], alpha_max)
        member, _, t_front = _walk(alpha, visible & (position < run_end[:, None]), t_front, threshold)
        # slot of each member: |M| so far + its rank in this step (1-based, past the non-member column)
        slot = torch.cumsum(member, dim=1)
        if count is not None:
            slot = slot + count[:, None]
        count = slot[:, -1]
        table.scatter_(1, slot * member, ids)
        walked = early_exit and step + 1 < steps
        if walked:
            open_run = torch.where(t_front > open_above, run_end - run_start, 0).max()
            values = read({"bound": count.max(), "open": open_run})
            bound = values["bound"]
            if values["open"] <= (step + 1) * width:
                break
    assert table is not None and count is not None  # steps >= 1: the caller walks non-empty runs only
    if not walked:
        bound = read({"bound": count.max()})["bound"]
    return table[:, 1 : bound + 1], count


def _run_entries(run_start: Tensor, flatten_ids: Tensor, begin: int, end: int) -> Tensor:
    """Ids at positions begin..end-1 of each pixel's run (clamped to the list): valid filler for unused slots."""
    position = run_start[:, None] + torch.arange(begin, end, device=run_start.device)
    return flatten_ids[position.clamp(0, max(flatten_ids.numel() - 1, 0))]


def vote_losses(
    render: VoteRender,
    target_xy: Tensor,
    valid: Tensor,
    options: Optional[VoteRenderOptions] = None,
    check_inputs: bool = True,
) -> Dict[str, Tensor]:
    """Vote loss (paper Eq. 10) and depth regulariser (Eq. 12), both unweighted.

    Args:
        render: output of a ``render_votes_*`` call for P pixels (and L levels).
        target_xy [P,2] (or [P,L,2] for a multi-level render): 2D target votes
            in the same continuous pixel frame (a mask centroid index c becomes
            c + 0.5). Entries where ``valid`` is False are ignored and may hold
            anything, NaN included.
        valid [P] (or [P,L]) bool: the pixel carries a 2D vote (at that level).
        options: only ``distortion == "none"`` matters here (zero regulariser).
        check_inputs: raise a ValueError when ``target_xy`` is not finite at a
            used pixel or the render holds NaN or inf (one host read). A caller
            whose targets are finite at valid pixels by construction and whose
            votes ``render_votes_*`` has checked may skip it: the loss is then
            NaN where these checks would have raised.

    Returns {"vote": mean over used pixels of |dx| + |dy| (the l1 norm),
    "distortion": mean of render.distortion over the same pixels}, where the
    used pixels are ``valid & (render.count > 0)``: scalars for a single-level
    render, tensors of shape [L] (one mean per level, over that level's used
    pixels) for a multi-level one. With no used pixel (empty pixel set, no
    valid pixel, nothing in view) a loss is 0 and still part of the graph,
    with zero gradient. The caller applies lambda_vote and lambda_d.
    """
    options = options or VoteRenderOptions()
    projected = render.projected_vote
    p = projected.shape[0]
    single = projected.ndim == 2
    levels = 1 if single else projected.shape[1]
    level_shape = (p,) if single else (p, levels)
    if tuple(target_xy.shape) != level_shape + (2,):
        raise ValueError(
            f"target_xy must have shape {list(level_shape + (2,))} like render.projected_vote, "
            f"got {list(target_xy.shape)}"
        )
    if tuple(valid.shape) != level_shape or valid.dtype != torch.bool:
        raise ValueError(
            f"valid must be a bool tensor of shape {list(level_shape)}, got {valid.dtype} {list(valid.shape)}"
        )
    projected = projected.reshape(p, levels, 2)
    distortion = render.distortion.reshape(p, levels)
    used = valid.reshape(p, levels) & (render.count > 0)[:, None]
    target = torch.where(used[..., None], target_xy.reshape(p, levels, 2).to(projected.dtype), 0.0)
    if check_inputs:
        _check_loss_inputs(target, projected, distortion)
    mask = used.to(projected.dtype)
    denominator = mask.sum(dim=0).clamp_min(1.0)
    error = (projected - target).abs().sum(dim=2)
    # Unused entries are finite (targets are masked, the render is finite), so multiplying by the
    # 0/1 mask gives what selecting them out would, in one op instead of two.
    vote = (error * mask).sum(dim=0) / denominator
    if options.distortion == "none":
        distortion = vote * 0.0
    else:
        distortion = (distortion * mask).sum(dim=0) / denominator
    if single:
        vote, distortion = vote[0], distortion[0]
    return {"vote": vote, "distortion": distortion}


def _check_loss_inputs(target: Tensor, projected: Tensor, distortion: Tensor) -> None:
    """vote_losses' input errors, with one host read (the per-input reads only on the error path)."""
    together = torch.cat([target.reshape(-1), projected.reshape(-1), distortion.reshape(-1)])
    if _read_host({"finite": _all_finite(together)})["finite"]:
        return
    _raise_unless(
        _read_host(
            {
                "target_xy contains NaN or inf at valid pixels; mark pixels without a 2D vote invalid": (
                    _all_finite(target)
                ),
                "the vote render contains NaN or inf; check the votes and the camera passed to the renderer": (
                    _all_finite(projected, distortion)
                ),
            }
        )
    )


# ---------------------------------------------------------------------------
# Shared pieces


def _validate_inputs(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    depths: Tensor,
    votes: Tensor,
    viewmat: Tensor,
    K: Tensor,
    pixel_xy: Tensor,
) -> Tuple[int, int, int]:
    """Shapes, dtypes and devices (no host read); returns (N, P, L), L = 1 for [N, 3] votes."""
    if votes.ndim not in (2, 3) or votes.shape[-1] != 3:
        raise ValueError(f"votes must have shape [N, 3] or [N, L, 3] (one vote per level), got {list(votes.shape)}")
    n = votes.shape[0]
    levels = 1 if votes.ndim == 2 else votes.shape[1]
    if levels < 1:
        raise ValueError(f"votes must have at least one level, got shape {list(votes.shape)}")
    shapes = {"means2d": (means2d, (n, 2)), "conics": (conics, (n, 3)), "opacities": (opacities, (n,))}
    _check_shapes(n, {**shapes, "depths": (depths, (n,))})
    if tuple(viewmat.shape) != (4, 4) or tuple(K.shape) != (3, 3):
        raise ValueError(
            f"viewmat must be [4, 4] and K [3, 3] for one camera, got {list(viewmat.shape)} and {list(K.shape)}"
        )
    if pixel_xy.ndim != 2 or pixel_xy.shape[1] != 2:
        raise ValueError(f"pixel_xy must have shape [P, 2], got {list(pixel_xy.shape)}")
    tensors = (means2d, conics, opacities, depths, votes, viewmat, K, pixel_xy)
    if any(not t.is_floating_point() for t in tensors):
        raise ValueError("means2d, conics, opacities, depths, votes, viewmat, K and pixel_xy must be floating point")
    if len({t.dtype for t in tensors}) != 1:
        raise ValueError("means2d, conics, opacities, depths, votes, viewmat, K and pixel_xy must share one dtype")
    if len({t.device for t in tensors}) != 1:
        raise ValueError("all inputs of the vote renderer must be on the same device")
    return n, pixel_xy.shape[0], levels


def _check_shapes(n: int, tensors: Dict[str, Tuple[Tensor, Tuple[int, ...]]]) -> None:
    """Raise at the first of ``tensors`` (name: (tensor, expected shape)) whose shape is not the expected
    one; n: the N read from votes."""
    for name, (t, shape) in tensors.items():
        if tuple(t.shape) != shape:
            raise ValueError(
                f"{name} must have shape {list(shape)} (N = {n} from votes), got {list(t.shape)}; "
                f"pass the tensors of one camera"
            )


DIVERGED_VOTES = "votes contain NaN or inf; the vote offsets have diverged (lower the learning rate or check the loss)"


def _finiteness_checks(votes: Tensor, pixel_xy: Tensor) -> Dict[str, Tensor]:
    """{error message: 0-d bool tensor that must be True}, to be read with one host sync."""
    return {
        DIVERGED_VOTES: _all_finite(votes),
        "pixel_xy contains NaN or inf; pass finite continuous pixel positions": _all_finite(pixel_xy),
    }


def _all_finite(*tensors: Tensor) -> Tensor:
    """0-d bool: every entry is finite (t * 0 is 0 for finite t, else NaN: 3 kernels, isfinite().all() takes 5)."""
    total = (tensors[0] * 0.0).sum()
    for t in tensors[1:]:
        total = total + (t * 0.0).sum()
    return total == 0.0


def _read_host(values: Dict[Any, Tensor]) -> Dict[Any, int]:
    """Several 0-d device values (bool or int) in one device-to-host copy: each separate read would be a sync."""
    if not values:
        return {}
    return dict(zip(values, torch.stack(list(values.values())).tolist()))


def _raise_unless(checks: Dict[str, int]) -> None:
    for message, ok in checks.items():
        if not ok:
            raise ValueError(message)


def _validate_tiles(
    isect_offsets: Tensor, flatten_ids: Tensor, tile_size: int, chunk: Optional[int], device: torch.device
) -> Tuple[Tensor, int, int]:
    """Shapes, dtypes and devices of the tile lists (their values are checked with the host read)."""
    if isect_offsets.ndim == 3 and isect_offsets.shape[0] == 1:
        isect_offsets = isect_offsets[0]
    if isect_offsets.ndim != 2:
        raise ValueError(
            f"isect_offsets must be [tile_height, tile_width] for one camera, got {list(isect_offsets.shape)}"
        )
    if isect_offsets.dtype.is_floating_point or flatten_ids.dtype.is_floating_point or flatten_ids.ndim != 1:
        raise ValueError("isect_offsets and flatten_ids must be integer tensors; flatten_ids must be 1-D")
    if isect_offsets.device != device or flatten_ids.device != device:
        raise ValueError("isect_offsets and flatten_ids must be on the same device as the Gaussians")
    if int(tile_size) != tile_size or tile_size < 1 or (chunk is not None and (int(chunk) != chunk or chunk < 1)):
        raise ValueError(f"tile_size and chunk must be positive integers, got {tile_size!r} and {chunk!r}")
    tiles_high, tiles_wide = isect_offsets.shape
    offsets = isect_offsets.reshape(-1)
    if offsets.dtype not in (torch.int32, torch.int64):  # gsplat's int32 serves as it is: no conversion op
        offsets = offsets.long()
    return offsets, tiles_high, tiles_wide


def _pixel_runs(
    pixel_xy: Tensor, offsets: Tensor, tiles_high: int, tiles_wide: int, tile_size: int, n_isects: int
) -> Tuple[Tensor, Tensor]:
    """[P] start and end of each pixel's tile run in flatten_ids; empty outside the tile grid."""
    if offsets.numel() == 0:
        empty = torch.zeros(pixel_xy.shape[0], dtype=torch.long, device=pixel_xy.device)
        return empty, empty
    tile = torch.floor(pixel_xy / tile_size)  # whole numbers, or NaN / inf
    tile_x = tile[:, 0]
    # The tile index in floating point: exact for whole numbers far beyond any tile grid.
    index = torch.add(tile_x, tile[:, 1], alpha=tiles_wide)
    # Clamped after the conversion, so any value (NaN, inf, out of the grid) gives a valid tile.
    tile_id = index.long().clamp(0, tiles_high * tiles_wide - 1)
    # In the grid: the column is in [0, tiles_wide) and the index in [0, tiles) (so the row is in
    # [0, tiles_high)). Compared with Python ints: a tensor built from host values would cost a
    # host-to-device copy and a sync.
    in_grid = (tile_x.clamp(0, tiles_wide - 1) == tile_x) & (tile_id == index)
    run_start = offsets[tile_id]
    ends = torch.cat([offsets[1:], offsets.new_full((1,), n_isects)])
    return run_start, torch.where(in_grid, ends[tile_id], run_start)


def _empty_render(p: int, votes: Tensor, viewmat: Tensor, K: Tensor, options: VoteRenderOptions) -> VoteRender:
    # Zeros that stay attached to the graph, so a loss built on them back-propagates (with zero gradient).
    anchor = votes.sum() * 0.0
    if not options.detach_geometry:
        anchor = anchor + (viewmat.sum() + K.sum()) * 0.0
    level_shape = (p,) if votes.ndim == 2 else (p, votes.shape[1])
    return VoteRender(
        mean_vote=votes.new_zeros(level_shape + (3,)) + anchor,
        projected_vote=votes.new_zeros(level_shape + (2,)) + anchor,
        count=torch.zeros(p, dtype=torch.long, device=votes.device),
        distortion=votes.new_zeros(level_shape) + anchor,
    )


def _geometry_table(means2d: Tensor, conics: Tensor, opacities: Tensor, options: VoteRenderOptions) -> Tensor:
    # One [N, 6] table so each chunk gathers its Gaussians with a single index.
    table = torch.cat([means2d, conics, opacities[:, None]], dim=1)
    return table.detach() if options.detach_geometry else table


def _camera(viewmat: Tensor, K: Tensor, options: VoteRenderOptions) -> Tuple[Tensor, Tensor]:
    if options.detach_geometry:
        return viewmat.detach(), K.detach()
    return viewmat, K


def _to_camera(points: Tensor, viewmat: Tensor) -> Tensor:
    return points @ viewmat[:3, :3].transpose(0, 1) + viewmat[:3, 3]


def _camera_to_pixels(cam: Tensor, K: Tensor, near_plane: float) -> Tensor:
    z = cam[..., 2:3].clamp_min(near_plane)
    return (cam[..., 0:2] / z) @ K[:2, :2].transpose(0, 1) + K[:2, 2]


def _vote_table(votes: Tensor, viewmat: Tensor, K: Tensor, options: VoteRenderOptions) -> Tensor:
    """[N, L, D] per Gaussian and level: the values to blend (world vote, plus its projection when
    blending in 2D), then the vote's camera depth last, so one gather fetches everything."""
    if options.blend_space == "2d":
        cam = _to_camera(votes, viewmat)
        return torch.cat([votes, _camera_to_pixels(cam, K, options.vote_near_plane), cam[..., 2:3]], dim=-1)
    depth = votes @ viewmat[2, :3] + viewmat[2, 3]
    return torch.cat([votes, depth[..., None]], dim=-1)


def _vote_threshold(options: VoteRenderOptions) -> float:
    return float(options.vote_transmittance) * (1.0 + VOTE_THRESHOLD_RTOL)


def _alpha(
    means2d: Tensor, conics: Tensor, opacities: Tensor, pixel_xy: Tensor, alpha_max: float
) -> Tuple[Tensor, Tensor]:
    """gsplat's per-pair alpha and whether the pair is composited at all (sigma >= 0, alpha >= 1/255)."""
    d = means2d - pixel_xy
    dx, dy = d[..., 0], d[..., 1]
    # sigma = 0.5 (a dx^2 + c dy^2) + b dx dy in few kernels (this runs on every pair): conics[..., 0::2] = (a, c).
    sigma = torch.add(conics[..., 1] * dx * dy, (d * d * conics[..., 0::2]).sum(dim=-1), alpha=0.5)
    # Pairs with sigma < 0 are skipped anyway; clamping keeps exp finite so their zero gradient is not 0 * inf.
    alpha = (opacities * torch.exp(-sigma.clamp_min(0.0))).clamp_max(alpha_max)
    visible = (sigma >= 0) & (alpha >= ALPHA_MIN)
    return alpha, visible


def _walk(alpha: Tensor, visible: Tensor, t_front: Optional[Tensor], threshold: float) -> Tuple[Tensor, Tensor, Tensor]:
    """Front-to-back walk over a block [p, L] that starts at transmittance t_front [p] (None: 1).

    Returns (member [p,L], T in front of each pair [p,L], T after the block
    [p]). Transmittance never rises, so "composited" and "member" are plain
    comparisons: once a pair ends the colour walk (T after it <= 1e-4), every
    later pair fails the same test, and once T in front is <= threshold it
    stays so. The pair that ends the colour walk still lowers T here, which
    is what keeps every later pair out.
    """
    effective = torch.where(visible, alpha, 0.0)
    t_after = torch.cumprod(1.0 - effective, dim=1)
    if t_front is None:  # multiplying by 1 is exact: skip it
        t_front = torch.ones_like(t_after[:, 0])
    else:
        t_after = t_front[:, None] * t_after
    t_before = torch.cat([t_front[:, None], t_after[:, :-1]], dim=1)
    member = visible & (t_after > COLOUR_STOP_T) & (t_before > threshold)
    return member, t_before, t_after[:, -1]


def _transmittance_in_front(alpha: Tensor) -> Tensor:
    """Transmittance in front of each entry of [p, M], starting from 1."""
    running = torch.cumprod(1.0 - alpha, dim=1)
    return torch.cat([torch.ones_like(running[:, :1]), running[:, :-1]], dim=1)


def _weights(member: Tensor, alpha: Tensor, t_before: Tensor, options: VoteRenderOptions) -> Tensor:
    if options.weighting == "alpha_t":
        return torch.where(member, alpha * t_before, 0.0)
    return member.to(alpha.dtype)


def _distortion(
    z: Tensor,
    member: Tensor,
    count: Tensor,
    value_sum: Tensor,
    options: VoteRenderOptions,
    K: Tensor,
    n_members: Optional[Tensor] = None,
    prefix: bool = False,
) -> Tensor:
    """[p, L] spread of the member vote depths z [p, M, L] (member [p, M], count [p] = its row sums).

    n_members: ``count`` in z's dtype, if the caller has it. prefix: the members are the first
    ``count`` slots of each row (the tiled table), so ``member`` is also the mask of the first
    ``count`` sorted ranks.
    """
    if options.distortion == "none":
        return value_sum[..., 0] * 0.0
    if n_members is None:
        n_members = count.to(z.dtype)
    if options.distortion == "l1":
        return _pairwise_l1(z, member, n_members, prefix)
    if options.distortion == "l1_pixels":
        n = n_members[:, None]
        pairs = (n * (n - 1.0) / 2.0).clamp_min(1.0)
        with torch.no_grad():
            mean_z = torch.where(member[..., None], z, 0.0).sum(dim=1) / n.clamp_min(1.0)
            pixels_per_unit = torch.sqrt(K[0, 0] * K[1, 1]) / mean_z.clamp_min(options.vote_near_plane)
        return _pairwise_l1(z, member, n_members, prefix) / pairs * pixels_per_unit
    if options.distortion == "squared":
        # sum over pairs of (z_i - z_j)^2 = n * sum_i (z_i - mean)^2
        mask = member.to(z.dtype)[..., None]
        n = n_members[:, None]
        mean = (mask * z).sum(dim=1) / n.clamp_min(1.0)
        return n * (mask * (z - mean[:, None]) ** 2).sum(dim=1)
    return value_sum[..., 0] * 0.0


def _pairwise_l1(z: Tensor, member: Tensor, n_members: Tensor, prefix: bool = False) -> Tensor:
    """Exact sum over member pairs i<j of |z_i - z_j| per row and level, via the sorted identity
    sum_k z_(k) (2k - m - 1) over the m members sorted (k from 1)."""
    # Non-members sort last behind the largest finite value (not inf, so that their zero
    # coefficient zeroes them without a mask: inf * 0 is NaN).
    big = torch.finfo(z.dtype).max
    ordered, _ = torch.sort(torch.where(member[..., None], z, big), dim=1)
    m = n_members[:, None]
    odd = torch.arange(1, 2 * z.shape[1], 2, device=z.device, dtype=z.dtype)  # 2k - 1
    gap = odd - m  # 2k - 1 - m: exact small integers
    in_set = member if prefix else gap < m  # k <= m
    coefficient = gap * in_set
    return (ordered * coefficient[..., None]).sum(dim=1)


def _finish(
    count: Tensor,
    weight_sum: Tensor,
    value_sum: Tensor,
    distortion: Tensor,
    viewmat: Tensor,
    K: Tensor,
    options: VoteRenderOptions,
    single_level: bool,
) -> VoteRender:
    """Normalise the [P, L, D] sums; empty pixels sum no weight, so their values and distortion are already 0."""
    has_votes = count > 0
    # Safe denominators: empty pixels divide by 1, so neither value nor gradient is NaN.
    if options.weighting == "uniform":  # weight_sum is |M|, a whole number: 0 becomes 1, the rest stay
        denominator = weight_sum.clamp_min(1.0)
    else:
        denominator = torch.where(has_votes, weight_sum, 1.0)
    blended = value_sum / denominator[:, None, None]
    mean_vote = blended[..., :3]
    if options.blend_space == "2d":
        projected = blended[..., 3:5]
    else:
        projected = project_to_pixels(mean_vote, viewmat, K, options.vote_near_plane)
        # empty pixels project the finite origin: zero them with the mask (one op, no scalar tensor)
        projected = projected * has_votes[:, None, None]
    if single_level:
        mean_vote, projected, distortion = mean_vote[:, 0], projected[:, 0], distortion[:, 0]
    return VoteRender(mean_vote=mean_vote, projected_vote=projected, count=count, distortion=distortion)
