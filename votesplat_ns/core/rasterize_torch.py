"""Pure-torch Gaussian splatting rasteriser with gsplat 1.4 semantics (CPU and CUDA).

gsplat 1.4.0's ``rasterization()`` JIT-builds CUDA code, so it cannot render on a CPU-only
machine. :func:`rasterize_torch` is a drop-in for the subset of it that nerfstudio 1.1.5's
splatfacto uses (``packed=False``, pinhole cameras), with the same outputs and the same
``info`` dictionary, so gsplat's ``DefaultStrategy`` and the vote renderer work unchanged.

Semantics follow gsplat 1.4.0's CUDA kernels (``gsplat/cuda/csrc``):

- projection (``fully_fused_projection_fwd.cu``): a Gaussian is culled (radius 0) when its
  camera depth is outside [near_plane, far_plane], when the blurred 2D covariance has
  det <= 0, when its radius is <= radius_clip, or when its radius box misses the image;
- tile lists (``isect_tiles.cu``): each Gaussian is listed in every tile its radius box
  touches, each tile's run is sorted front to back by depth (ties by flattened index);
- compositing (``rasterize_to_pixels_fwd.cu``), per pixel, front to back:
  sigma = 0.5 * (a dx^2 + c dy^2) + b dx dy with d = mean2d - pixel centre; skip if
  sigma < 0; alpha = min(alpha_max, opacity * exp(-sigma)); skip if alpha < 1/255;
  next_T = T (1 - alpha); stop, without this Gaussian, once next_T <= 1e-4.
  gsplat 1.4.0 clamps alpha at 0.999 (``min(0.999f, ...)`` in the forward and backward
  kernels); ``alpha_max`` defaults to that value.

Rendering is done in two passes so that only the (pixel, Gaussian) pairs that actually
contribute are ever differentiated:

1. selection (no grad): each tile's depth-sorted run is split into runs for 8x8-pixel
   blocks, dropping Gaussians whose alpha >= 1/255 ellipse misses the block (they would be
   skipped at every pixel there anyway). Blocks of similar run length are walked together
   densely, [blocks, pixels, candidates] in steps of bounded size, with the kernel's
   sequential transmittance (cumprod, T carried between steps); the 1e-4 stop is the mask
   ``next_T > 1e-4``, exact because T never grows. Saturated blocks drop out early.
2. compositing (``_CompositePairs``): alpha is recomputed for the selected pairs only, T as
   exp of a per-pixel exclusive sum of log(1 - alpha) (float64), with a hand-written
   backward that is gsplat's backward kernel in vectorised form (and AbsGS's absgrad).

Everything is plain torch, so it also runs on CUDA (the tests compare it there with
gsplat's kernels), though on a GPU gsplat itself is the faster choice.

No nerfstudio import here: this module is torch-only.
"""

from __future__ import annotations

import math
from typing import Any, Dict, List, Optional, Tuple

import torch

# gsplat's own pure-torch helpers; they are exact re-implementations of its CUDA maths.
from gsplat.cuda._torch_impl import _persp_proj, _quat_scale_to_covar_preci, _spherical_harmonics, _world_to_cam
from torch import Tensor
from torch.autograd.function import once_differentiable

GSPLAT_ALPHA_MAX = 0.999
"""Upper clamp on a Gaussian's alpha in gsplat 1.4.0's kernels."""

ALPHA_MIN = 1.0 / 255.0
"""Gaussians with alpha below this are skipped (they neither add colour nor occlude)."""

TRANSMITTANCE_STOP = 1e-4
"""A pixel stops before the Gaussian that would bring its transmittance to or below this."""

DEFAULT_CHUNK_ELEMENTS = 1 << 21
"""Elements of one dense [blocks, pixels, candidates] step of the selection pass."""

DEFAULT_BLOCK_SIZE = 8
"""Side in pixels of the blocks each tile's run is culled to (must divide tile_size)."""

DEFAULT_K_CHUNK = 128
"""Candidates per step of the selection pass; saturated blocks drop out between steps."""

DEFAULT_MAX_PAIRS = 1 << 22
"""Contributing pairs per step of the differentiable pass."""

RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
RASTERIZE_MODES = ("classic", "antialiased")

# gsplat.rendering.rasterization arguments that splatfacto (or other callers) may pass
# and that need no action here, with the value that is the only one supported.
_ACCEPTED_GSPLAT_ARGS = {
    "sparse_grad": None,  # only changes gradient layout for packed mode
    "channel_chunk": None,  # a CUDA kernel size limit; we render any number of channels
    "distributed": False,
    "camera_model": "pinhole",
    "covars": None,
}


# ----------------------------------------------------------------------------------------
# projection
# ----------------------------------------------------------------------------------------


def project_gaussians_torch(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    calc_compensations: bool = False,
) -> Tuple[Tensor, Tensor, Tensor, Tensor, Optional[Tensor]]:
    """Project 3D Gaussians to C pinhole cameras as gsplat 1.4's ``fully_fused_projection``.

    Args:
        means [N,3], quats [N,4] (wxyz, any norm), scales [N,3] (already exp'd),
        viewmats [C,4,4] world-to-camera (OpenCV), Ks [C,3,3], width/height in pixels.

    Returns:
        radii [C,N] int32 (0 = culled), means2d [C,N,2], depths [C,N] (camera z),
        conics [C,N,3] (a, b, c of the inverse blurred 2D covariance), compensations [C,N]
        (sqrt(det(cov2d) / det(cov2d + eps2d I)), or None unless ``calc_compensations``).
        For culled Gaussians means2d, conics and compensations are 0; depths are the true
        camera z. Everything but radii is differentiable.
    """
    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False)
    assert covars is not None  # compute_covar=True
    means_c, covars_c = _world_to_cam(means, covars, viewmats)  # [C,N,3], [C,N,3,3]
    depths = means_c[..., 2]

    depth_ok = (depths >= near_plane) & (depths <= far_plane)
    # Culled Gaussians may sit on the camera plane (z = 0); feeding them through the
    # projection would make inf/NaN that poison gradients even behind a torch.where.
    safe_point = means_c.new_tensor([0.0, 0.0, 1.0])
    means_c_safe = torch.where(depth_ok[..., None], means_c, safe_point)
    means2d, covars2d = _persp_proj(means_c_safe, covars_c, Ks, width, height)

    c00, c01, c10, c11 = covars2d[..., 0, 0], covars2d[..., 0, 1], covars2d[..., 1, 0], covars2d[..., 1, 1]
    det_orig = c00 * c11 - c01 * c10
    c00 = c00 + eps2d
    c11 = c11 + eps2d
    det = c00 * c11 - c01 * c10
    det_ok = det > 0
    det_safe = torch.where(det_ok, det, torch.ones_like(det))
    conics = torch.stack([c11 / det_safe, -0.5 * (c01 + c10) / det_safe, c00 / det_safe], dim=-1)

    compensations = None
    if calc_compensations:
        ratio = det_orig / det_safe
        positive = ratio > 0
        # sqrt has an infinite slope at 0: keep masked entries away from it (gsplat's
        # backward uses 1 / (comp + 1e-6) for the same reason).
        compensations = torch.where(positive, torch.sqrt(torch.where(positive, ratio, torch.ones_like(ratio))), 0.0)

    with torch.no_grad():
        b = 0.5 * (c00 + c11)
        v1 = b + torch.sqrt(torch.clamp(b * b - det, min=0.01))
        radius = torch.ceil(3.0 * torch.sqrt(v1))
        m2 = means2d.detach()
        inside = (
            (m2[..., 0] + radius > 0)
            & (m2[..., 0] - radius < width)
            & (m2[..., 1] + radius > 0)
            & (m2[..., 1] - radius < height)
        )
        valid = depth_ok & det_ok & (radius > radius_clip) & inside
        radii = torch.where(valid, radius, torch.zeros_like(radius)).to(torch.int32)

    zero = means2d.new_zeros(())
    means2d = torch.where(valid[..., None], means2d, zero)
    conics = torch.where(valid[..., None], conics, zero)
    if compensations is not None:
        compensations = torch.where(valid, compensations, zero)
    return radii, means2d, depths, conics, compensations


# ----------------------------------------------------------------------------------------
# tile intersection
# ----------------------------------------------------------------------------------------


@torch.no_grad()
def _isect_tiles_with_ids(
    means2d: Tensor, radii: Tensor, depths: Tensor, tile_size: int, tile_width: int, tile_height: int
) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`isect_tiles_torch` plus gsplat's 64-bit ``isect_ids`` (sorted)."""
    if means2d.dim() != 3 or means2d.shape[-1] != 2:
        raise ValueError(f"means2d must be [C, N, 2] (unpacked), got {tuple(means2d.shape)}")
    C, N = means2d.shape[:2]
    if radii.shape != (C, N) or depths.shape != (C, N):
        raise ValueError(
            f"radii and depths must be [C, N] = {(C, N)}, got {tuple(radii.shape)} and {tuple(depths.shape)}"
        )
    device = means2d.device
    n_tiles = tile_width * tile_height
    tile_n_bits = n_tiles.bit_length()
    cam_n_bits = max(C, 1).bit_length()
    if tile_n_bits + cam_n_bits > 32:
        raise ValueError(
            f"{C} cameras x {n_tiles} tiles do not fit gsplat's 32-bit camera|tile key; render fewer cameras at once"
        )

    valid = radii > 0
    # Same float arithmetic as the kernel (means2d's dtype), then the kernel's saturating
    # float->uint conversion and clamp to the tile grid.
    m2 = torch.where(valid[..., None], means2d, torch.zeros_like(means2d))
    tile_radius = radii.to(m2.dtype) / tile_size
    tile_x = m2[..., 0] / tile_size
    tile_y = m2[..., 1] / tile_size
    x_min = torch.floor(tile_x - tile_radius).clamp(0, tile_width).long()
    y_min = torch.floor(tile_y - tile_radius).clamp(0, tile_height).long()
    x_max = torch.ceil(tile_x + tile_radius).clamp(0, tile_width).long()
    y_max = torch.ceil(tile_y + tile_radius).clamp(0, tile_height).long()
    tiles_per_gauss = torch.where(valid, (x_max - x_min) * (y_max - y_min), 0)  # [C,N] int64

    counts = tiles_per_gauss.reshape(-1)
    n_isects = int(counts.sum().item())
    if n_isects == 0:
        empty_i32 = torch.zeros(0, dtype=torch.int32, device=device)
        return (
            tiles_per_gauss.to(torch.int32),
            torch.zeros((C, tile_height, tile_width), dtype=torch.int32, device=device),
            empty_i32,
            torch.zeros(0, dtype=torch.int64, device=device),
        )

    # Enumerate (gaussian, tile) pairs in the kernel's order: flattened index, then the
    # Gaussian's tile box row-major.
    flat_index = torch.repeat_interleave(torch.arange(C * N, device=device), counts)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(n_isects, device=device) - first.index_select(0, flat_index)
    box_w = (x_max - x_min).reshape(-1).index_select(0, flat_index)
    tile_x_id = x_min.reshape(-1).index_select(0, flat_index) + local % box_w
    tile_y_id = y_min.reshape(-1).index_select(0, flat_index) + local // box_w
    cam = flat_index // N
    tile_id = tile_y_id * tile_width + tile_x_id
    key = cam * n_tiles + tile_id

    # gsplat radix-sorts (camera | tile | float32 depth bits) stably. For the positive
    # depths that survive culling, float order equals bit order, so a stable sort by depth
    # followed by a stable sort by (camera, tile) gives the same order, also for float64.
    isect_depth = depths.reshape(-1).index_select(0, flat_index)
    order = torch.argsort(isect_depth, stable=True)
    order = order.index_select(0, torch.argsort(key.index_select(0, order), stable=True))
    flat_sorted = flat_index.index_select(0, order)
    key_sorted = key.index_select(0, order)

    depth_bits = isect_depth.index_select(0, order).to(torch.float32).contiguous().view(torch.int32).to(torch.int64)
    isect_ids = (cam.index_select(0, order) << (32 + tile_n_bits)) | (tile_id.index_select(0, order) << 32) | depth_bits

    tile_counts = torch.bincount(key_sorted, minlength=C * n_tiles)
    offsets = (torch.cumsum(tile_counts, 0) - tile_counts).to(torch.int32)
    return (
        tiles_per_gauss.to(torch.int32),
        offsets.reshape(C, tile_height, tile_width),
        flat_sorted.to(torch.int32),
        isect_ids,
    )


def isect_tiles_torch(
    means2d: Tensor, radii: Tensor, depths: Tensor, tile_size: int, tile_width: int, tile_height: int
) -> Tuple[Tensor, Tensor, Tensor]:
    """Tile/Gaussian intersection lists in gsplat 1.4's layout (pure torch, CPU or CUDA).

    Args:
        means2d [C,N,2], radii [C,N] (int, 0 = culled), depths [C,N]: as projected.
        tile_size: tile side in pixels; tile_width/tile_height: the tile grid
        (ceil(width / tile_size), ceil(height / tile_size)).

    Returns:
        tiles_per_gauss [C,N] int32: tiles touched by each Gaussian's radius box.
        isect_offsets [C, tile_height, tile_width] int32: start of each tile's run in
            flatten_ids (an empty tile's start equals the next run's start; the last
            tile's run ends at len(flatten_ids)).
        flatten_ids [n_isects] int32: indices into the C*N flattened Gaussians (camera
            major), runs ordered by (camera, tile row-major), each run front to back by
            depth, ties by flattened index.
    """
    tiles_per_gauss, offsets, flatten_ids, _ = _isect_tiles_with_ids(
        means2d, radii, depths, tile_size, tile_width, tile_height
    )
    return tiles_per_gauss, offsets, flatten_ids


# ----------------------------------------------------------------------------------------
# compositing
# ----------------------------------------------------------------------------------------


def _pair_alpha(rows: Tensor, pixel_x: Tensor, pixel_y: Tensor, alpha_max: float):
    """alpha = min(alpha_max, o exp(-sigma)) per pair (rows: [mx, my, a, b, c, o, ...] x P),
    and the pieces its gradient needs."""
    dx = rows[0] - pixel_x
    dy = rows[1] - pixel_y
    sigma = 0.5 * (rows[2] * dx * dx + rows[4] * dy * dy) + rows[3] * dx * dy
    falloff = torch.exp(-sigma)
    unclamped = rows[5] * falloff
    return torch.clamp(unclamped, max=alpha_max), unclamped, falloff, dx, dy


class _CompositePairs(torch.autograd.Function):
    """Alpha compositing of (pixel, Gaussian) pairs with a hand-written backward.

    Pairs come grouped by pixel, front to back; ``pixel_of_pair`` numbers the pixels
    0..S-1 in that order and ``pixel_start`` [S] is the index of each pixel's first pair.
    ``table_t`` is [6 + D, C*N] with rows mean x, mean y, conic a,
    b, c, opacity, colour... (column-major so every per-pair quantity is a contiguous
    vector). Outputs per pixel: colour [S, D] = sum_i alpha_i T_i c_i and the final
    transmittance [S] = prod_i (1 - alpha_i), with T_i = prod_{j<i} (1 - alpha_j) taken as
    exp of a per-pixel exclusive sum of log(1 - alpha) (float64 running sums).

    The backward is gsplat's (rasterize_to_pixels_bwd.cu) in vectorised form, including
    no gradient through the alpha clamp; it also adds AbsGS's |d loss / d mean2d| per pair
    into ``abs_buffer`` ([2, C*N]) when one is given.
    """

    @staticmethod
    def forward(ctx, table_t, gaussian, pixel_x, pixel_y, pixel_of_pair, pixel_start, alpha_max, abs_buffer):  # type: ignore[override]
        rows = table_t.index_select(1, gaussian)  # [6 + D, P]
        alpha = _pair_alpha(rows, pixel_x, pixel_y, alpha_max)[0]
        log_keep = torch.log1p(-alpha).double()
        inclusive = torch.cumsum(log_keep, 0)
        exclusive = inclusive - log_keep
        before_pixel = exclusive.index_select(0, pixel_start)
        transmittance = torch.exp(exclusive - before_pixel.index_select(0, pixel_of_pair)).to(alpha.dtype)
        weight = alpha * transmittance
        n_pixels = pixel_start.shape[0]
        colour = rows.new_zeros((rows.shape[0] - 6, n_pixels)).index_add_(1, pixel_of_pair, rows[6:] * weight)
        pixel_end = torch.cat([pixel_start[1:], pixel_start.new_tensor([alpha.shape[0]])])
        final_t = torch.exp(inclusive.index_select(0, pixel_end - 1) - before_pixel).to(alpha.dtype)
        ctx.save_for_backward(rows, gaussian, pixel_x, pixel_y, pixel_of_pair, pixel_end, transmittance, final_t)
        ctx.alpha_max = alpha_max
        ctx.abs_buffer = abs_buffer
        ctx.n_gaussians = table_t.shape[1]
        return colour.t(), final_t

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_colour, grad_final_t):  # type: ignore[override]
        rows, gaussian, pixel_x, pixel_y, pixel_of_pair, pixel_end, transmittance, final_t = ctx.saved_tensors
        alpha, unclamped, falloff, dx, dy = _pair_alpha(rows, pixel_x, pixel_y, ctx.alpha_max)
        grad_colour_pair = grad_colour.t().contiguous().index_select(1, pixel_of_pair)  # [D, P]
        weight = alpha * transmittance
        colour_dot = (rows[6:] * grad_colour_pair).sum(0)  # c_i . dL/dC
        # behind_i = sum over the pixel's later pairs j of w_j (c_j . dL/dC)
        inclusive = torch.cumsum((weight * colour_dot).double(), 0)
        pixel_total = inclusive.index_select(0, pixel_end - 1)
        behind = (pixel_total.index_select(0, pixel_of_pair) - inclusive).to(alpha.dtype)
        final_t_term = (grad_final_t * final_t).index_select(0, pixel_of_pair)
        # dC/d alpha_i = T_i c_i - behind_i / (1 - alpha_i); dT_final/d alpha_i = -T_final / (1 - alpha_i)
        grad_alpha = transmittance * colour_dot - (behind + final_t_term) / (1.0 - alpha)
        grad_alpha = torch.where(unclamped <= ctx.alpha_max, grad_alpha, 0.0)
        grad_sigma = -unclamped * grad_alpha
        a, b, c = rows[2], rows[3], rows[4]
        grad_rows = torch.empty_like(rows)
        torch.mul(grad_sigma, a * dx + b * dy, out=grad_rows[0])
        torch.mul(grad_sigma, b * dx + c * dy, out=grad_rows[1])
        torch.mul(0.5 * grad_sigma, dx * dx, out=grad_rows[2])
        torch.mul(grad_sigma * dx, dy, out=grad_rows[3])
        torch.mul(0.5 * grad_sigma, dy * dy, out=grad_rows[4])
        torch.mul(falloff, grad_alpha, out=grad_rows[5])
        torch.mul(grad_colour_pair, weight, out=grad_rows[6:])
        if ctx.abs_buffer is not None:
            ctx.abs_buffer.index_add_(1, gaussian, grad_rows[:2].abs())
        grad_table = rows.new_zeros((rows.shape[0], ctx.n_gaussians)).index_add_(1, gaussian, grad_rows)
        return grad_table, None, None, None, None, None, None, None


@torch.no_grad()
def _block_candidate_lists(
    means2d_flat: Tensor,
    conics_flat: Tensor,
    opacities_flat: Tensor,
    isect_offsets: Tensor,
    flatten_ids: Tensor,
    width: int,
    height: int,
    tile_size: int,
    block_size: int,
) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Split each tile's run into runs for its block_size x block_size pixel blocks.

    A Gaussian stays in a block's run only if its alpha >= 1/255 ellipse
    (sigma <= ln(255 * opacity)) can reach a pixel centre of the block: every other
    candidate would be skipped at every pixel of the block anyway, so dropping it changes
    nothing but the work. The test is conservative: the ellipse's bounding box, padded so
    that float32 rounding in the walk cannot revive a dropped pair.

    Returns (block_ids [B], run_starts [B], run_counts [B], candidates [M]): the blocks
    with a non-empty run (global block index: camera-major, block rows row-major), where
    each block's run lies in ``candidates``, and ``candidates``, indices into flatten_ids,
    each run front to back.
    """
    device = means2d_flat.device
    C, tile_height, tile_width = isect_offsets.shape
    n_isects = flatten_ids.numel()
    sub = tile_size // block_size
    n_sub = sub * sub
    tiles_per_camera = tile_width * tile_height
    n_tiles = C * tiles_per_camera

    run_starts = isect_offsets.reshape(-1).long()
    run_ends = torch.cat([run_starts[1:], run_starts.new_tensor([n_isects])])
    tile_of_entry = torch.repeat_interleave(torch.arange(n_tiles, device=device), run_ends - run_starts)

    # Per Gaussian: half-extents of the alpha >= 1/255 ellipse (inf where the conic is not
    # positive definite, so such a Gaussian is never dropped).
    mean = means2d_flat.double()
    a, b, c = conics_flat.double().unbind(-1)
    det = a * c - b * b
    definite = (det > 0) & (a > 0)
    level = torch.log(torch.clamp(opacities_flat.double(), min=1e-300) * 255.0) + 1e-3
    reachable = (level >= 0) | ~definite
    level = level.clamp(min=0.0)
    det_safe = torch.where(definite, det, torch.ones_like(det))
    # x-extent of {d : 0.5 d^T Q d <= L} is sqrt(2 L (Q^-1)_xx), (Q^-1)_xx = c / det(Q).
    inf = torch.full_like(det, float("inf"))
    extent_x = torch.where(definite, torch.sqrt(2.0 * level * c / det_safe) * (1 + 1e-5) + 1e-4, inf)
    extent_y = torch.where(definite, torch.sqrt(2.0 * level * a / det_safe) * (1 + 1e-5) + 1e-4, inf)

    # Pixel-centre span of each tile's sub-blocks, clipped to the image.
    tile = torch.arange(n_tiles, device=device)
    tile_row = (tile % tiles_per_camera) // tile_width
    tile_col = tile % tile_width
    step = torch.arange(sub, device=device)
    block_x0 = tile_col[:, None] * tile_size + step[None, :] * block_size  # [tiles, sub]
    block_y0 = tile_row[:, None] * tile_size + step[None, :] * block_size
    first_x = block_x0.double() + 0.5
    first_y = block_y0.double() + 0.5
    last_x = torch.clamp(first_x + (block_size - 1), max=width - 0.5)
    last_y = torch.clamp(first_y + (block_size - 1), max=height - 0.5)

    gid = flatten_ids.long()
    ex = extent_x.gather(0, gid)[:, None]
    ey = extent_y.gather(0, gid)[:, None]
    mx = mean[:, 0].gather(0, gid)[:, None]
    my = mean[:, 1].gather(0, gid)[:, None]
    hit_x = (mx + ex >= first_x[tile_of_entry]) & (mx - ex <= last_x[tile_of_entry]) & (block_x0[tile_of_entry] < width)
    hit_y = (
        (my + ey >= first_y[tile_of_entry]) & (my - ey <= last_y[tile_of_entry]) & (block_y0[tile_of_entry] < height)
    )
    hit = hit_y[:, :, None] & hit_x[:, None, :] & reachable.gather(0, gid)[:, None, None]
    hit = hit.reshape(n_isects, n_sub)

    # Regroup the kept entries block by block with a counting sort: tile runs are already
    # contiguous and front to back, so ranks within a tile keep depth order.
    kept_before = torch.cat([torch.zeros((1, n_sub), dtype=torch.long, device=device), torch.cumsum(hit, 0)])
    tile_first = kept_before[run_starts]  # [tiles, n_sub]: kept entries before each tile run
    per_block = (kept_before[run_ends] - tile_first).reshape(-1)  # [tiles * n_sub]
    block_first = torch.cumsum(per_block, 0) - per_block
    entry, sub_index = hit.nonzero(as_tuple=True)
    block_of_entry = tile_of_entry.gather(0, entry) * n_sub + sub_index  # (tile, sub-block)
    rank = (
        kept_before[1:].reshape(-1).gather(0, entry * n_sub + sub_index)
        - tile_first.reshape(-1).gather(0, block_of_entry)
        - 1
    )
    destination = block_first.gather(0, block_of_entry) + rank
    candidates = torch.empty_like(entry).index_copy_(0, destination, entry)

    busy = torch.nonzero(per_block > 0).squeeze(1)  # (tile, sub-block) ids with a run
    busy_tile = busy // n_sub
    busy_sub = busy % n_sub
    blocks_wide = tile_width * sub
    block_ids = (
        (busy_tile // tiles_per_camera) * (tile_height * sub * blocks_wide)
        + (tile_row[busy_tile] * sub + busy_sub // sub) * blocks_wide
        + tile_col[busy_tile] * sub
        + busy_sub % sub
    )
    return block_ids, block_first[busy], per_block[busy], candidates


@torch.no_grad()
def _walk_block_group(
    block_ids: Tensor,
    starts: Tensor,
    counts: Tensor,
    candidates: Tensor,
    means2d_flat: Tensor,
    conics_flat: Tensor,
    opacities_flat: Tensor,
    flatten_ids: Tensor,
    width: int,
    height: int,
    block_size: int,
    blocks_wide: int,
    blocks_per_camera: int,
    alpha_max: float,
    k_chunk: int,
) -> Tuple[Tensor, Tensor]:
    """Walk a group of blocks front to back with gsplat's rule; return contributing pairs.

    Returns (pixel [P], gaussian [P]): group-local pixel index (block in group * bs^2 +
    row * bs + col) and flattened Gaussian index of every contributing pair, each
    pixel's pairs contiguous and front to back.
    """
    device = means2d_flat.device
    dtype = means2d_flat.dtype
    bs = block_size
    pixels_per_block = bs * bs
    n_group = block_ids.shape[0]
    block_in_cam = block_ids % blocks_per_camera
    steps = torch.arange(bs, device=device)
    rows = (block_in_cam // blocks_wide)[:, None] * bs + steps[None, :]  # [G, bs]
    cols = (block_in_cam % blocks_wide)[:, None] * bs + steps[None, :]
    centre_x = cols.to(dtype) + 0.5
    centre_y = rows.to(dtype) + 0.5
    inside = (rows[:, :, None] < height) & (cols[:, None, :] < width)  # [G, bs, bs]

    transmittance = inside.to(dtype)  # pixels outside the image start out "done"
    in_block = torch.arange(pixels_per_block, device=device)
    active = torch.arange(n_group, device=device)
    longest = int(counts.max().item())
    found_pixel: List[Tensor] = []
    found_gid: List[Tensor] = []
    for k0 in range(0, longest, k_chunk):
        k1 = min(k0 + k_chunk, longest)
        n_k = k1 - k0
        k = torch.arange(k0, k1, device=device)
        run_count = counts[active]
        in_run = k[None, :] < run_count[:, None]  # [A, kc]
        entry = torch.where(in_run, starts[active][:, None] + k[None, :], 0)
        gid = flatten_ids[candidates[entry]].long()
        mean = means2d_flat[gid]  # [A, kc, 2]
        conic = conics_flat[gid]
        opacity = opacities_flat[gid] * in_run  # padding gets opacity 0
        # Sigma separates over the pixel grid: dx depends on the column, dy on the row.
        dx = mean[:, None, :, 0] - centre_x[active][:, :, None]  # [A, col, kc]
        dy = mean[:, None, :, 1] - centre_y[active][:, :, None]  # [A, row, kc]
        a = conic[:, None, :, 0]
        b = conic[:, None, :, 1]
        c = conic[:, None, :, 2]
        # Built as -sigma so that exp can run in place.
        neg_sigma = (-b * dx)[:, None, :, :] * dy[:, :, None, :]  # [A, row, col, kc]
        neg_sigma -= (0.5 * a * dx * dx)[:, None, :, :]
        neg_sigma -= (0.5 * c * dy * dy)[:, :, None, :]
        # alpha < 1/255  <=>  o exp(-sigma) < 1/255  <=>  -sigma < -ln(255 o)
        faint_below = torch.where(opacity > 0, -torch.log(opacity * 255.0), torch.inf)
        skip = neg_sigma < faint_below[:, None, None, :]
        definite = (conic[..., 0] > 0) & (conic[..., 0] * conic[..., 2] > conic[..., 1] * conic[..., 1])
        if not bool(definite.all()):  # sigma < 0 is only possible for an indefinite conic
            skip |= neg_sigma > 0
        factor = neg_sigma.exp_()
        # 1 - alpha = max(1 - alpha_max, 1 - o exp(-sigma))
        torch.addcmul(
            torch.ones((), dtype=dtype, device=device), factor, opacity[:, None, None, :], value=-1.0, out=factor
        )
        factor.clamp_(min=1.0 - alpha_max)
        factor.masked_fill_(skip, 1.0)
        # Carry T in as the first factor: cumprod then multiplies in exactly the kernel's
        # sequential order, and everything after the stop has next_T <= 1e-4 as well.
        factor[..., 0] *= transmittance[active]
        next_t = torch.cumprod(factor, dim=-1)
        transmittance[active] = next_t[..., -1]
        next_t.masked_fill_(skip, 0.0)
        contributes = next_t.reshape(-1, n_k) > TRANSMITTANCE_STOP  # [A * bs^2, kc]
        row_index, kk = contributes.nonzero(as_tuple=True)  # pixel by pixel, front to back
        if row_index.numel():
            # lookup tables per row of `contributes` (gathers are much cheaper than // and %)
            pixel_of_row = (active[:, None] * pixels_per_block + in_block[None, :]).reshape(-1)
            slot_of_row = torch.arange(active.numel(), device=device).repeat_interleave(pixels_per_block)
            found_pixel.append(pixel_of_row.gather(0, row_index))
            found_gid.append(gid.reshape(-1).gather(0, slot_of_row.gather(0, row_index) * n_k + kk))
        still = (transmittance[active] > TRANSMITTANCE_STOP).flatten(1).any(dim=1) & (run_count > k1)
        active = active[still]
        if active.numel() == 0:
            break

    if not found_pixel:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return empty, empty
    if len(found_pixel) > 1:
        # Later chunks append to pixels found before: counting-sort the pairs by pixel.
        # Within a chunk nonzero listed them pixel by pixel, front to back, so a pair's
        # place is: pairs of earlier pixels + pairs of its pixel in earlier chunks + its
        # rank among its pixel's pairs in this chunk.
        n_pixels = n_group * pixels_per_block
        earlier_chunks = torch.zeros(n_pixels, dtype=torch.long, device=device)
        ranks = []
        for pixel in found_pixel:
            n_found = pixel.shape[0]
            new_pixel = torch.ones(n_found, dtype=torch.bool, device=device)
            new_pixel[1:] = pixel[1:] != pixel[:-1]
            position = torch.arange(n_found, device=device)
            run_first = torch.cummax(torch.where(new_pixel, position, 0), 0).values
            ranks.append(position - run_first + earlier_chunks.gather(0, pixel))
            earlier_chunks += torch.bincount(pixel, minlength=n_pixels)
        pixel_first = torch.cumsum(earlier_chunks, 0) - earlier_chunks
        pixel = torch.cat(found_pixel)
        destination = pixel_first.gather(0, pixel) + torch.cat(ranks)
        pixel = torch.empty_like(pixel).index_copy_(0, destination, pixel)
        gaussian = torch.empty_like(pixel).index_copy_(0, destination, torch.cat(found_gid))
    else:
        pixel, gaussian = found_pixel[0], found_gid[0]
    return pixel, gaussian


@torch.no_grad()
def _contributing_pairs(
    means2d_flat: Tensor,
    conics_flat: Tensor,
    opacities_flat: Tensor,
    isect_offsets: Tensor,
    flatten_ids: Tensor,
    width: int,
    height: int,
    tile_size: int,
    alpha_max: float,
    block_size: int,
    chunk_elements: int,
    k_chunk: int,
) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """All contributing (pixel, Gaussian) pairs of the render, each pixel's pairs
    contiguous and front to back.

    Returns (pixel [P] global index camera * H * W + y * W + x, pixel centre x [P] and
    y [P], flattened Gaussian index [P]).
    """
    device = means2d_flat.device
    dtype = means2d_flat.dtype
    if block_size <= 0 or tile_size % block_size != 0:
        block_size = tile_size
    empty = torch.zeros(0, dtype=torch.long, device=device)
    if flatten_ids.numel() == 0:
        return empty, empty.to(dtype), empty.to(dtype), empty
    blocks, starts, counts, candidates = _block_candidate_lists(
        means2d_flat, conics_flat, opacities_flat, isect_offsets, flatten_ids, width, height, tile_size, block_size
    )
    if blocks.numel() == 0:
        return empty, empty.to(dtype), empty.to(dtype), empty
    # Longest runs first so that each group pads little to its longest run.
    order = torch.argsort(counts, descending=True, stable=True)
    blocks, counts, starts = blocks[order], counts[order], starts[order]
    counts_list = counts.tolist()
    sub = tile_size // block_size
    blocks_wide = isect_offsets.shape[-1] * sub
    blocks_per_camera = isect_offsets.shape[-2] * sub * blocks_wide
    pixels_per_block = block_size * block_size
    in_block = torch.arange(pixels_per_block, device=device)

    pixels: List[Tensor] = []
    xs: List[Tensor] = []
    ys: List[Tensor] = []
    gaussians: List[Tensor] = []
    at = 0
    while at < len(counts_list):
        width_k = min(counts_list[at], k_chunk)
        n_group = max(1, chunk_elements // (pixels_per_block * width_k))
        group = blocks[at : at + n_group]
        local_pixel, gaussian = _walk_block_group(
            group,
            starts[at : at + n_group],
            counts[at : at + n_group],
            candidates,
            means2d_flat,
            conics_flat,
            opacities_flat,
            flatten_ids,
            width,
            height,
            block_size,
            blocks_wide,
            blocks_per_camera,
            alpha_max,
            k_chunk,
        )
        at += n_group
        # group-local pixel -> image coordinates through small lookup tables
        block_in_cam = group % blocks_per_camera
        x = ((block_in_cam % blocks_wide) * block_size)[:, None] + in_block[None, :] % block_size
        y = ((block_in_cam // blocks_wide) * block_size)[:, None] + in_block[None, :] // block_size
        index = (group // blocks_per_camera)[:, None] * (height * width) + y * width + x
        pixels.append(index.reshape(-1).gather(0, local_pixel))
        xs.append((x.reshape(-1).to(dtype) + 0.5).gather(0, local_pixel))
        ys.append((y.reshape(-1).to(dtype) + 0.5).gather(0, local_pixel))
        gaussians.append(gaussian)
    return torch.cat(pixels), torch.cat(xs), torch.cat(ys), torch.cat(gaussians)


def rasterize_to_pixels_torch(
    means2d: Tensor,
    conics: Tensor,
    colors: Tensor,
    opacities: Tensor,
    width: int,
    height: int,
    tile_size: int,
    isect_offsets: Tensor,
    flatten_ids: Tensor,
    backgrounds: Optional[Tensor] = None,
    absgrad: bool = False,
    alpha_max: float = GSPLAT_ALPHA_MAX,
    chunk_elements: int = DEFAULT_CHUNK_ELEMENTS,
    block_size: int = DEFAULT_BLOCK_SIZE,
    k_chunk: int = DEFAULT_K_CHUNK,
    max_pairs: int = DEFAULT_MAX_PAIRS,
) -> Tuple[Tensor, Tensor]:
    """Alpha-composite projected Gaussians, as gsplat 1.4's ``rasterize_to_pixels``.

    Args:
        means2d [C,N,2], conics [C,N,3], colors [C,N,D], opacities [C,N]; isect_offsets
        [C,tile_height,tile_width] and flatten_ids from :func:`isect_tiles_torch`;
        backgrounds [C,D] or None (added as T_final * background).
        absgrad: after backward, ``means2d.absgrad`` holds the sum over pixels of the
            absolute per-pixel gradient of each 2D mean (the attribute is attached here and
            filled during backward).
        chunk_elements, block_size, k_chunk, max_pairs: speed/memory knobs of the two
            passes (dense block size, culling block side, candidates per step, pairs per
            differentiable step); they do not change the result.

    Returns:
        render_colors [C,H,W,D], render_alphas [C,H,W,1] (= 1 - final transmittance).
    """
    if means2d.dim() != 3 or means2d.shape[-1] != 2:
        raise ValueError(f"means2d must be [C, N, 2] (unpacked), got {tuple(means2d.shape)}")
    C, N = means2d.shape[:2]
    if conics.shape != (C, N, 3) or opacities.shape != (C, N) or colors.dim() != 3 or colors.shape[:2] != (C, N):
        raise ValueError(
            f"expected conics [C,N,3], opacities [C,N], colors [C,N,D] with C,N = {C},{N}; got "
            f"{tuple(conics.shape)}, {tuple(opacities.shape)}, {tuple(colors.shape)}"
        )
    D = colors.shape[-1]
    tile_height, tile_width = math.ceil(height / tile_size), math.ceil(width / tile_size)
    if isect_offsets.shape != (C, tile_height, tile_width):
        raise ValueError(
            f"isect_offsets must be [C, tile_height, tile_width] = {(C, tile_height, tile_width)} for a "
            f"{width}x{height} image with tile_size {tile_size}, got {tuple(isect_offsets.shape)}"
        )
    if backgrounds is not None and backgrounds.shape != (C, D):
        raise ValueError(f"backgrounds must be [C, D] = {(C, D)}, got {tuple(backgrounds.shape)}")
    device = means2d.device
    dtype = means2d.dtype

    means2d_flat = means2d.reshape(C * N, 2)
    conics_flat = conics.reshape(C * N, 3)
    opacities_flat = opacities.reshape(C * N)
    colors_flat = colors.reshape(C * N, D)

    pixel, pixel_x, pixel_y, gaussian = _contributing_pairs(
        means2d_flat.detach(),
        conics_flat.detach(),
        opacities_flat.detach(),
        isect_offsets,
        flatten_ids,
        width,
        height,
        tile_size,
        alpha_max,
        block_size,
        chunk_elements,
        k_chunk,
    )

    absgrad_buffer = None
    if absgrad:
        absgrad_buffer = torch.zeros((2, C * N), dtype=dtype, device=device)
        if means2d.requires_grad:
            # gsplat's convention: the accumulated |grad| rides on the tensor as .absgrad
            means2d.absgrad = absgrad_buffer.t().view(C, N, 2)  # pyright: ignore[reportAttributeAccessIssue]

    n_pixels = C * height * width
    render_colors = torch.zeros((n_pixels, D), dtype=colors.dtype, device=device)
    final_transmittance = torch.ones(n_pixels, dtype=dtype, device=device)
    if pixel.numel():
        table_t = torch.cat([means2d_flat.t(), conics_flat.t(), opacities_flat[None, :], colors_flat.t().to(dtype)])
        # Split at pixel boundaries so each differentiable step stays bounded in memory.
        n_pairs = pixel.numel()
        new_pixel = torch.ones_like(pixel, dtype=torch.bool)
        new_pixel[1:] = pixel[1:] != pixel[:-1]
        pixel_starts = torch.nonzero(new_pixel).squeeze(1)
        bounds = [0]
        while n_pairs - bounds[-1] > max_pairs:
            i = int(torch.searchsorted(pixel_starts, bounds[-1] + max_pairs).item())
            if i >= pixel_starts.numel():
                break
            bounds.append(int(pixel_starts[i].item()))
        bounds.append(n_pairs)
        pixel_number = torch.cumsum(new_pixel, 0) - 1  # 0.. over all pixels present
        found_colours, found_t = [], []
        for lo, hi in zip(bounds[:-1], bounds[1:]):
            first_pixel = int(pixel_number[lo].item())
            starts = pixel_starts[first_pixel : int(pixel_number[hi - 1].item()) + 1] - lo
            colour, final_t = _CompositePairs.apply(
                table_t,
                gaussian[lo:hi],
                pixel_x[lo:hi],
                pixel_y[lo:hi],
                pixel_number[lo:hi] - first_pixel,
                starts,
                alpha_max,
                absgrad_buffer,
            )
            found_colours.append(colour)
            found_t.append(final_t)
        index = pixel.index_select(0, pixel_starts)
        render_colors = render_colors.index_copy(0, index, torch.cat(found_colours).to(colors.dtype))
        final_transmittance = final_transmittance.index_copy(0, index, torch.cat(found_t))
    render_colors = render_colors.reshape(C, height, width, D)
    final_transmittance = final_transmittance.reshape(C, height, width, 1)
    if backgrounds is not None:
        render_colors = render_colors + final_transmittance * backgrounds[:, None, None, :]
    return render_colors, 1.0 - final_transmittance


# ----------------------------------------------------------------------------------------
# the rasterization() drop-in
# ----------------------------------------------------------------------------------------


# the tensor arguments of rasterize_torch, in the order their values are checked
_INPUT_NAMES = ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")


def _check_finite(name: str, tensor: Tensor) -> None:
    if not bool(torch.isfinite(tensor).all()):
        raise ValueError(f"{name} contains NaN or inf; fix the upstream parameters before rendering")


def _check_gsplat_extras(extras: Dict[str, Any]) -> None:
    for name, value in extras.items():
        if name not in _ACCEPTED_GSPLAT_ARGS:
            raise TypeError(f"rasterize_torch() got an unexpected keyword argument {name!r}")
        supported = _ACCEPTED_GSPLAT_ARGS[name]
        if supported is not None and value != supported:
            raise ValueError(f"rasterize_torch supports only {name}={supported!r}; got {value!r}")
        if name == "covars" and value is not None:
            raise ValueError("rasterize_torch takes quats and scales, not covars; pass covars=None")


def _validate_options(
    width: int, height: int, tile_size: int, render_mode: str, rasterize_mode: str, packed: bool
) -> None:
    if packed:
        raise ValueError("rasterize_torch renders unpacked only; pass packed=False")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    if rasterize_mode not in RASTERIZE_MODES:
        raise ValueError(f"rasterize_mode must be one of {RASTERIZE_MODES}, got {rasterize_mode!r}")
    if int(width) <= 0 or int(height) <= 0 or int(tile_size) <= 0:
        raise ValueError(f"width, height and tile_size must be positive, got {width}, {height}, {tile_size}")


def _validate_shapes(gaussians: Tuple[Tensor, Tensor, Tensor, Tensor], viewmats: Tensor, Ks: Tensor) -> Tuple[int, int]:
    """(N, C) after checking ``gaussians`` = (means, quats, scales, opacities) and the cameras."""
    means, quats, scales, opacities = gaussians
    if means.dim() != 2 or means.shape[1] != 3:
        raise ValueError(f"means must be [N, 3], got {tuple(means.shape)}")
    N = means.shape[0]
    if quats.shape != (N, 4):
        raise ValueError(f"quats must be [N, 4] = {(N, 4)} (wxyz), got {tuple(quats.shape)}")
    if scales.shape != (N, 3):
        raise ValueError(f"scales must be [N, 3] = {(N, 3)} (already exp'd), got {tuple(scales.shape)}")
    if opacities.shape != (N,):
        raise ValueError(f"opacities must be [N] = {(N,)} (already sigmoid'd), got {tuple(opacities.shape)}")
    if viewmats.dim() != 3 or viewmats.shape[1:] != (4, 4):
        raise ValueError(f"viewmats must be [C, 4, 4], got {tuple(viewmats.shape)}")
    C = viewmats.shape[0]
    if Ks.shape != (C, 3, 3):
        raise ValueError(f"Ks must be [C, 3, 3] = {(C, 3, 3)}, got {tuple(Ks.shape)}")
    return N, C


def _validate_colors(colors: Tensor, sh_degree: Optional[int], backgrounds: Optional[Tensor], N: int, C: int) -> None:
    if sh_degree is None:
        if not ((colors.dim() == 2 and colors.shape[0] == N) or (colors.dim() == 3 and colors.shape[:2] == (C, N))):
            raise ValueError(
                f"with sh_degree=None colors must be [N, D] or [C, N, D] post-activation values, got {tuple(colors.shape)}"
            )
    else:
        if sh_degree < 0:
            raise ValueError(f"sh_degree must be >= 0 or None, got {sh_degree}")
        ok = (colors.dim() == 3 and colors.shape[0] == N and colors.shape[2] == 3) or (
            colors.dim() == 4 and colors.shape[:2] == (C, N) and colors.shape[3] == 3
        )
        if not ok:
            raise ValueError(
                f"with sh_degree set colors must be SH coefficients [N, K, 3] or [C, N, K, 3], got {tuple(colors.shape)}"
            )
        if (sh_degree + 1) ** 2 > colors.shape[-2]:
            raise ValueError(
                f"sh_degree={sh_degree} needs {(sh_degree + 1) ** 2} SH bases but colors has {colors.shape[-2]}; lower sh_degree"
            )
    if backgrounds is not None:
        D = 3 if sh_degree is not None else colors.shape[-1]
        if backgrounds.shape != (C, D):
            raise ValueError(f"backgrounds must be [C, D] = {(C, D)}, got {tuple(backgrounds.shape)}")


def rasterize_torch(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: Optional[int] = None,
    packed: bool = False,
    tile_size: int = 16,
    backgrounds: Optional[Tensor] = None,
    render_mode: str = "RGB",
    rasterize_mode: str = "classic",
    absgrad: bool = False,
    alpha_max: float = GSPLAT_ALPHA_MAX,
    chunk_elements: int = DEFAULT_CHUNK_ELEMENTS,
    **ignored: Any,
) -> Tuple[Tensor, Tensor, Dict[str, Any]]:
    """Drop-in for ``gsplat.rendering.rasterization`` (unpacked, pinhole), pure torch.

    Arguments and outputs are gsplat 1.4.0's: render_colors [C,H,W,X] (X = D, 1 for
    "D"/"ED", D+1 for "RGB+D"/"RGB+ED" with depth last; "ED" divides accumulated depth by
    max(alpha, 1e-10)), render_alphas [C,H,W,1], and info with "camera_ids" (None),
    "gaussian_ids" (None), "radii" [C,N] int32, "means2d" [C,N,2] (in the autograd graph:
    ``retain_grad()`` before backward gives the 2D-mean gradient; with absgrad=True
    ``.absgrad`` holds AbsGS's gradient after backward), "depths", "conics", "opacities"
    (times the antialiasing compensation in "antialiased" mode), "tile_width",
    "tile_height", "tiles_per_gauss", "isect_ids", "flatten_ids", "isect_offsets",
    "width", "height", "tile_size", "n_cameras".

    ``sparse_grad`` and ``channel_chunk`` are accepted and have no effect; ``packed=True``,
    ``distributed=True``, ``camera_model != "pinhole"`` and ``covars`` raise ValueError.
    ``alpha_max`` (gsplat: 0.999) and ``chunk_elements`` (memory bound) are extras.
    """
    _check_gsplat_extras(ignored)
    _validate_options(width, height, tile_size, render_mode, rasterize_mode, packed)
    gaussians = (means, quats, scales, opacities)
    N, C = _validate_shapes(gaussians, viewmats, Ks)
    _validate_colors(colors, sh_degree, backgrounds, N, C)
    for name, tensor in zip(_INPUT_NAMES, (*gaussians, colors, viewmats, Ks)):
        _check_finite(name, tensor)
    width, height, tile_size = int(width), int(height), int(tile_size)

    radii, means2d, depths, conics, compensations = project_gaussians_torch(
        means,
        quats,
        scales,
        viewmats,
        Ks,
        width,
        height,
        eps2d=eps2d,
        near_plane=near_plane,
        far_plane=far_plane,
        radius_clip=radius_clip,
        calc_compensations=(rasterize_mode == "antialiased"),
    )
    view_opacities = opacities.repeat(C, 1)
    if compensations is not None:
        view_opacities = view_opacities * compensations

    if sh_degree is None:
        view_colors = colors.expand(C, -1, -1) if colors.dim() == 2 else colors
    else:
        camera_centres = torch.inverse(viewmats)[:, :3, 3]  # [C,3]
        directions = means[None, :, :] - camera_centres[:, None, :]
        coeffs = colors.expand(C, -1, -1, -1) if colors.dim() == 3 else colors
        # gsplat evaluates SH only for visible Gaussians; a culled one may sit exactly at
        # the camera centre, where normalising the direction has no gradient.
        directions = torch.where((radii > 0)[..., None], directions, directions.new_tensor([0.0, 0.0, 1.0]))
        view_colors = torch.clamp_min(_spherical_harmonics(sh_degree, directions, coeffs) + 0.5, 0.0)

    if render_mode in ("RGB+D", "RGB+ED"):
        view_colors = torch.cat([view_colors, depths[..., None]], dim=-1)
        if backgrounds is not None:
            backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(C, 1)], dim=-1)
    elif render_mode in ("D", "ED"):
        view_colors = depths[..., None]
        if backgrounds is not None:
            backgrounds = backgrounds.new_zeros(C, 1)

    tile_width = math.ceil(width / tile_size)
    tile_height = math.ceil(height / tile_size)
    tiles_per_gauss, isect_offsets, flatten_ids, isect_ids = _isect_tiles_with_ids(
        means2d.detach(), radii, depths.detach(), tile_size, tile_width, tile_height
    )

    render_colors, render_alphas = rasterize_to_pixels_torch(
        means2d,
        conics,
        view_colors,
        view_opacities,
        width,
        height,
        tile_size,
        isect_offsets,
        flatten_ids,
        backgrounds=backgrounds,
        absgrad=absgrad,
        alpha_max=alpha_max,
        chunk_elements=chunk_elements,
    )
    if render_mode in ("ED", "RGB+ED"):
        render_colors = torch.cat(
            [render_colors[..., :-1], render_colors[..., -1:] / render_alphas.clamp(min=1e-10)], dim=-1
        )

    info: Dict[str, Any] = {
        "camera_ids": None,
        "gaussian_ids": None,
        "radii": radii,
        "means2d": means2d,
        "depths": depths,
        "conics": conics,
        "opacities": view_opacities,
        "tile_width": tile_width,
        "tile_height": tile_height,
        "tiles_per_gauss": tiles_per_gauss,
        "isect_ids": isect_ids,
        "flatten_ids": flatten_ids,
        "isect_offsets": isect_offsets,
        "width": width,
        "height": height,
        "tile_size": tile_size,
        "n_cameras": C,
    }
    return render_colors, render_alphas, info
