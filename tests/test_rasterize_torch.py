"""The pure-torch rasteriser against a brute-force per-pixel reference and gsplat's own
reference implementations (values and gradients, float64)."""

from __future__ import annotations

import math
from typing import Dict, List, Optional, Tuple

import pytest
import torch
from gsplat.cuda._torch_impl import (
    _fully_fused_projection,
    _isect_offset_encode,
    _isect_tiles,
    _quat_scale_to_covar_preci,
    _spherical_harmonics,
)

from votesplat_ns.core.rasterize_torch import (
    ALPHA_MIN,
    GSPLAT_ALPHA_MAX,
    TRANSMITTANCE_STOP,
    isect_tiles_torch,
    project_gaussians_torch,
    rasterize_to_pixels_torch,
    rasterize_torch,
)

# ---------------------------------------------------------------------------------------
# scenes
# ---------------------------------------------------------------------------------------


def _look_at_viewmat(eye, target) -> torch.Tensor:
    """World-to-camera matrix (OpenCV axes: x right, y down, z forward)."""
    eye = torch.tensor(eye, dtype=torch.float64)
    forward = torch.tensor(target, dtype=torch.float64) - eye
    forward = forward / forward.norm()
    right = torch.linalg.cross(forward, torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64))
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    rotation = torch.stack([right, down, forward])  # rows: camera axes in world
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = rotation
    viewmat[:3, 3] = -rotation @ eye
    return viewmat


def make_scene(
    seed: int,
    n_gaussians: int = 48,
    n_cameras: int = 2,
    width: int = 37,
    height: int = 29,
    sh_degree: Optional[int] = 3,
    dtype: torch.dtype = torch.float64,
) -> Dict[str, object]:
    """Random Gaussians around the origin seen by cameras on a circle.

    The mix is chosen so every branch of the rules is exercised: large opaque Gaussians
    stacked in depth (alpha clamp and the 1e-4 stop), faint ones (alpha < 1/255), some
    behind the camera or far off screen (culled), and some straddling the image border.
    """
    gen = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=gen, dtype=torch.float64)

    def randn(*shape):
        return torch.randn(*shape, generator=gen, dtype=torch.float64)

    n = n_gaussians
    means = (rand(n, 3) - 0.5) * torch.tensor([2.4, 2.0, 2.0], dtype=torch.float64)
    means[: n // 8] += torch.tensor([0.0, 0.0, -4.5])  # behind the first camera
    means[n // 8 : n // 4, 0] += 3.0  # off screen to the side
    quats = randn(n, 4)
    scales = torch.exp(randn(n, 3) * 0.6) * 0.08
    scales[: n // 3] *= 3.0  # big enough to span tiles
    opacities = rand(n) * 0.9 + 0.05
    opacities[: n // 2] = 0.97 + 0.03 * rand(n // 2)  # saturating layers
    opacities[n // 4 : n // 2] = 0.9995 + 0.0004 * rand(n // 2 - n // 4)  # alpha reaches the clamp
    # A stack of opaque Gaussians straight ahead of every camera (the 1e-4 stop); the first
    # sits at the origin, which the first camera sees exactly at a pixel centre when width
    # and height are odd, so its alpha reaches the clamp there.
    stack = [(0.0, 0.0, 0.0)] + [(0.05 * (-1) ** k, -0.02 * k, 0.15 * k) for k in range(1, 6)]
    means[n // 2 : n // 2 + 6] = torch.tensor(stack, dtype=torch.float64)
    scales[n // 2 : n // 2 + 6] = 0.15
    opacities[n // 2 : n // 2 + 6] = 0.9998
    opacities[-3:] = 0.004  # alpha < 1/255 everywhere
    if sh_degree is None:
        colors = rand(n, 3)
    else:
        colors = randn(n, (sh_degree + 1) ** 2, 3) * 0.4
    eyes = [(0.0, -0.3, -3.0), (2.2, 0.4, -2.2), (-2.0, -0.8, -2.4)]
    viewmats = torch.stack([_look_at_viewmat(eyes[i], (0.0, 0.0, 0.0)) for i in range(n_cameras)])
    focal = [40.0, 47.0, 36.0]
    Ks = torch.stack(
        [
            torch.tensor(
                [[focal[i], 0.0, width / 2 + 1.3 * i], [0.0, focal[i] * 1.05, height / 2 - 0.7 * i], [0, 0, 1]],
                dtype=torch.float64,
            )
            for i in range(n_cameras)
        ]
    )
    backgrounds = rand(n_cameras, 3)
    scene = dict(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=colors,
        viewmats=viewmats,
        Ks=Ks,
        backgrounds=backgrounds,
    )
    scene = {k: v.to(dtype) for k, v in scene.items()}
    scene.update(width=width, height=height, sh_degree=sh_degree)
    return scene


DIFFERENTIABLE = ("means", "quats", "scales", "opacities", "colors", "viewmats", "backgrounds")


def _leaves(scene, names=DIFFERENTIABLE):
    return {k: scene[k].detach().clone().requires_grad_(k in names) for k in DIFFERENTIABLE + ("Ks",)}


# ---------------------------------------------------------------------------------------
# brute-force reference
# ---------------------------------------------------------------------------------------


def reference_project(leaves, width, height, eps2d=0.3, near_plane=0.01, far_plane=1e10, antialiased=False):
    """gsplat's own pure-torch projection (gsplat/cuda/_torch_impl.py)."""
    covars, _ = _quat_scale_to_covar_preci(leaves["quats"], leaves["scales"], compute_preci=False)
    radii, means2d, depths, conics, compensations = _fully_fused_projection(
        leaves["means"],
        covars,
        leaves["viewmats"],
        leaves["Ks"],
        width,
        height,
        eps2d=eps2d,
        near_plane=near_plane,
        far_plane=far_plane,
        calc_compensations=antialiased,
    )
    return radii, means2d, depths, conics, compensations


def reference_colors(leaves, sh_degree, radii):
    C = leaves["viewmats"].shape[0]
    if sh_degree is None:
        return leaves["colors"].expand(C, -1, -1)
    centres = torch.inverse(leaves["viewmats"])[:, :3, 3]
    dirs = leaves["means"][None] - centres[:, None]
    coeffs = leaves["colors"].expand(C, -1, -1, -1)
    return torch.clamp_min(_spherical_harmonics(sh_degree, dirs, coeffs) + 0.5, 0.0)


def _in_tile_box(mx, my, radius, tile_x, tile_y, tile_size, tile_width, tile_height):
    """gsplat's tile box of a Gaussian (isect_tiles.cu), written out for one tile."""
    r = radius / tile_size
    x_min = min(max(math.floor(mx / tile_size - r), 0), tile_width)
    y_min = min(max(math.floor(my / tile_size - r), 0), tile_height)
    x_max = min(max(math.ceil(mx / tile_size + r), 0), tile_width)
    y_max = min(max(math.ceil(my / tile_size + r), 0), tile_height)
    return x_min <= tile_x < x_max and y_min <= tile_y < y_max


def reference_composite(
    means2d,
    conics,
    colors,
    opacities,
    radii,
    depths,
    width,
    height,
    tile_size=16,
    backgrounds=None,
    alpha_max=GSPLAT_ALPHA_MAX,
    stats=None,
):
    """Per pixel, every visible Gaussian front to back, the rule applied literally.

    The decisions are made with Python floats; the chosen Gaussians' weights are then
    recomputed with torch (sequential cumprod per pixel) so autograd gives the reference
    gradients.
    Returns colours [C,H,W,D] and alphas [C,H,W,1] and, per pixel, the chosen indices.
    """
    C, N = radii.shape
    D = colors.shape[-1]
    tile_width = math.ceil(width / tile_size)
    tile_height = math.ceil(height / tile_size)
    m2 = means2d.detach().tolist()
    con = conics.detach().tolist()
    op = opacities.detach().tolist()
    dep = depths.detach().tolist()
    rad = radii.tolist()
    images, alpha_images, chosen_all = [], [], []
    for cam in range(C):
        visible = sorted((i for i in range(N) if rad[cam][i] > 0), key=lambda i: (dep[cam][i], i))
        chosen_cam = []
        for y in range(height):
            for x in range(width):
                T = 1.0
                chosen: List[int] = []
                for i in visible:
                    mx, my = m2[cam][i]
                    if not _in_tile_box(
                        mx, my, rad[cam][i], x // tile_size, y // tile_size, tile_size, tile_width, tile_height
                    ):
                        continue
                    a, b, c = con[cam][i]
                    dx, dy = mx - (x + 0.5), my - (y + 0.5)
                    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                    if sigma < 0:
                        continue
                    alpha = min(alpha_max, op[cam][i] * math.exp(-sigma))
                    if alpha < ALPHA_MIN:
                        continue
                    if stats is not None and alpha == alpha_max:
                        stats["clamped"] += 1
                    next_t = T * (1.0 - alpha)
                    if next_t <= TRANSMITTANCE_STOP:
                        if stats is not None:
                            stats["stopped"] += 1
                        break
                    chosen.append(i)
                    T = next_t
                chosen_cam.append(chosen)
        # Differentiable recomputation of the chosen Gaussians' weights, all pixels at once
        # (padded to the longest list; padding has alpha 0).
        longest = max([1, *(len(ch) for ch in chosen_cam)])
        index = torch.zeros(height * width, longest, dtype=torch.long)
        used = torch.zeros(height * width, longest, dtype=torch.bool)
        for p, ch in enumerate(chosen_cam):
            index[p, : len(ch)] = torch.tensor(ch, dtype=torch.long)
            used[p, : len(ch)] = True
        ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
        centres = torch.stack([xs, ys], -1).reshape(-1, 1, 2).to(means2d.dtype) + 0.5
        d = means2d[cam][index] - centres
        q = conics[cam][index]
        sig = 0.5 * (q[..., 0] * d[..., 0] ** 2 + q[..., 2] * d[..., 1] ** 2) + q[..., 1] * d[..., 0] * d[..., 1]
        alphas = torch.clamp(opacities[cam][index] * torch.exp(-sig), max=alpha_max) * used
        keep = 1.0 - alphas
        trans = torch.cumprod(torch.cat([keep.new_ones(height * width, 1), keep[:, :-1]], 1), 1)
        colour = ((alphas * trans)[..., None] * colors[cam][index]).sum(1)
        final_t = torch.prod(keep, 1)
        if backgrounds is not None:
            colour = colour + final_t[:, None] * backgrounds[cam]
        images.append(colour.reshape(height, width, D))
        alpha_images.append((1.0 - final_t).reshape(height, width, 1))
        chosen_all.append(chosen_cam)
    return torch.stack(images), torch.stack(alpha_images), chosen_all


def reference_rasterize(
    leaves,
    width,
    height,
    sh_degree,
    render_mode="RGB",
    use_background=True,
    antialiased=False,
    tile_size=16,
    stats=None,
):
    radii, means2d, depths, conics, compensations = reference_project(leaves, width, height, antialiased=antialiased)
    C, N = radii.shape
    opacities = leaves["opacities"][None].expand(C, N)
    if compensations is not None:
        opacities = opacities * compensations
    colors = reference_colors(leaves, sh_degree, radii)
    backgrounds = leaves["backgrounds"] if use_background else None
    if render_mode in ("RGB+D", "RGB+ED"):
        colors = torch.cat([colors, depths[..., None]], -1)
        if backgrounds is not None:
            backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(C, 1)], -1)
    elif render_mode in ("D", "ED"):
        colors = depths[..., None]
        backgrounds = None if backgrounds is None else backgrounds.new_zeros(C, 1)
    image, alpha, _ = reference_composite(
        means2d, conics, colors, opacities, radii, depths, width, height, tile_size, backgrounds, stats=stats
    )
    if render_mode in ("ED", "RGB+ED"):
        image = torch.cat([image[..., :-1], image[..., -1:] / alpha.clamp(min=1e-10)], -1)
    return image, alpha, radii


def _fast(leaves, scene, render_mode="RGB", use_background=True, antialiased=False, tile_size=16, **kwargs):
    return rasterize_torch(
        leaves["means"],
        leaves["quats"],
        leaves["scales"],
        leaves["opacities"],
        leaves["colors"],
        leaves["viewmats"],
        leaves["Ks"],
        scene["width"],
        scene["height"],
        sh_degree=scene["sh_degree"],
        backgrounds=leaves["backgrounds"] if use_background else None,
        render_mode=render_mode,
        rasterize_mode="antialiased" if antialiased else "classic",
        tile_size=tile_size,
        **kwargs,
    )


def _grads(outputs, leaves, weights):
    loss = sum((o * w).sum() for o, w in zip(outputs, weights))
    names = [k for k in DIFFERENTIABLE if leaves[k].requires_grad]
    grads = torch.autograd.grad(loss, [leaves[k] for k in names], allow_unused=True)
    return {k: (torch.zeros_like(leaves[k]) if g is None else g) for k, g in zip(names, grads)}


# ---------------------------------------------------------------------------------------
# tests: rendering against the reference
# ---------------------------------------------------------------------------------------


CASES = [
    # id, seed, sh_degree, render_mode, background, antialiased, n_cameras, tile_size
    ("rgb_sh3_bg_2cams", 0, 3, "RGB", True, False, 2, 16),
    ("rgbed_sh0_bg", 1, 0, "RGB+ED", True, False, 2, 16),
    ("rgbed_sh3_nobg_3cams", 2, 3, "RGB+ED", False, False, 3, 16),
    ("rgb_plain_colors_tile8", 3, None, "RGB", True, False, 1, 8),
    ("rgbd_sh1_antialiased", 4, 1, "RGB+D", True, True, 2, 16),
    ("ed_only", 5, 2, "ED", False, False, 1, 16),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_matches_brute_force_reference_values_and_gradients(case):
    _, seed, sh_degree, render_mode, use_background, antialiased, n_cameras, tile_size = case
    scene = make_scene(seed, n_cameras=n_cameras, sh_degree=sh_degree)
    stats = {"clamped": 0, "stopped": 0}

    ref_leaves = _leaves(scene)
    ref_image, ref_alpha, ref_radii = reference_rasterize(
        ref_leaves,
        scene["width"],
        scene["height"],
        sh_degree,
        render_mode,
        use_background,
        antialiased,
        tile_size,
        stats,
    )
    fast_leaves = _leaves(scene)
    image, alpha, info = _fast(fast_leaves, scene, render_mode, use_background, antialiased, tile_size)

    # the scene exercises every rule: culling, the 0.999 clamp, the 1e-4 stop
    assert (ref_radii == 0).any() and (ref_radii > 0).any()
    assert stats["stopped"] > 0
    assert stats["clamped"] > 0 or antialiased  # compensation keeps alpha below the clamp
    assert (alpha > 0.5).any() and (alpha == 0).any()

    assert torch.equal(info["radii"], ref_radii.to(torch.int32))
    assert image.shape == ref_image.shape and alpha.shape == ref_alpha.shape
    torch.testing.assert_close(image, ref_image, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(alpha, ref_alpha, rtol=1e-9, atol=1e-10)

    gen = torch.Generator().manual_seed(100 + seed)
    weights = [
        torch.randn(image.shape, generator=gen, dtype=image.dtype),
        torch.randn(alpha.shape, generator=gen, dtype=alpha.dtype),
    ]
    ref_grads = _grads((ref_image, ref_alpha), ref_leaves, weights)
    fast_grads = _grads((image, alpha), fast_leaves, weights)
    for name in ref_grads:
        assert torch.isfinite(fast_grads[name]).all(), name
        torch.testing.assert_close(fast_grads[name], ref_grads[name], rtol=1e-7, atol=1e-9, msg=name)
    assert fast_grads["means"].abs().sum() > 0
    assert (fast_grads["colors"].abs().sum() > 0) == render_mode.startswith("RGB")


def test_float32_close_to_float64_reference():
    scene = make_scene(7, n_cameras=1, sh_degree=3)
    ref_leaves = _leaves(scene)
    ref_image, ref_alpha, _ = reference_rasterize(ref_leaves, scene["width"], scene["height"], 3, "RGB+ED")
    scene32 = make_scene(7, n_cameras=1, sh_degree=3, dtype=torch.float32)
    image, alpha, _ = _fast(_leaves(scene32), scene32, "RGB+ED")
    assert image.dtype == torch.float32 and alpha.dtype == torch.float32
    torch.testing.assert_close(image.double(), ref_image, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(alpha.double(), ref_alpha, rtol=1e-4, atol=1e-4)


def test_alpha_max_is_configurable():
    """gsplat 1.4.0's kernels clamp alpha at 0.999 (the default); other clamps, such as the
    0.99 of the original 3DGS rasteriser, follow the same rule."""
    scene = make_scene(8, n_cameras=1, sh_degree=None)
    leaves = _leaves(scene)
    radii, means2d, depths, conics, _ = reference_project(leaves, scene["width"], scene["height"])
    colors = reference_colors(leaves, None, radii)
    opacities = leaves["opacities"][None].expand_as(depths)
    for alpha_max in (0.99, GSPLAT_ALPHA_MAX):
        ref_image, ref_alpha, _ = reference_composite(
            means2d, conics, colors, opacities, radii, depths, scene["width"], scene["height"], alpha_max=alpha_max
        )
        image, alpha, _ = _fast(leaves, scene, use_background=False, alpha_max=alpha_max)
        torch.testing.assert_close(image, ref_image, rtol=1e-9, atol=1e-10)
        torch.testing.assert_close(alpha, ref_alpha, rtol=1e-9, atol=1e-10)


def test_chunking_knobs_do_not_change_the_result():
    scene = make_scene(9, n_gaussians=64, n_cameras=2)
    leaves = _leaves(scene)
    _, _, info = _fast(leaves, scene, "RGB+ED")
    colors = torch.cat([reference_colors(leaves, 3, info["radii"]), info["depths"][..., None]], -1)

    def render(**knobs):
        return rasterize_to_pixels_torch(
            info["means2d"],
            info["conics"],
            colors,
            info["opacities"],
            scene["width"],
            scene["height"],
            16,
            info["isect_offsets"],
            info["flatten_ids"],
            **knobs,
        )

    default = render()
    for knobs in (
        dict(chunk_elements=512, block_size=2, k_chunk=7, max_pairs=50),
        dict(chunk_elements=1 << 12, block_size=16, k_chunk=5, max_pairs=37),
        dict(chunk_elements=1 << 24, block_size=3, k_chunk=10_000),  # 3 does not divide 16
    ):
        image, alpha = render(**knobs)
        torch.testing.assert_close(image, default[0], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(alpha, default[1], rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------------------------------
# tests: info for splatfacto / DefaultStrategy / the vote renderer
# ---------------------------------------------------------------------------------------


def test_info_means2d_grad_and_absgrad_match_per_pixel_reference():
    scene = make_scene(10, n_gaussians=24, n_cameras=2, width=19, height=11, sh_degree=1)
    leaves = _leaves(scene)
    image, alpha, info = _fast(leaves, scene, "RGB", absgrad=True)
    info["means2d"].retain_grad()
    gen = torch.Generator().manual_seed(3)
    w_image = torch.randn(image.shape, generator=gen, dtype=image.dtype)
    w_alpha = torch.randn(alpha.shape, generator=gen, dtype=alpha.dtype)
    ((image * w_image).sum() + (alpha * w_alpha).sum()).backward()
    grad = info["means2d"].grad
    absgrad = info["means2d"].absgrad
    assert grad is not None and grad.shape == info["means2d"].shape
    assert absgrad.shape == info["means2d"].shape

    # Reference: composite from leaf copies of the projected quantities, pixel by pixel.
    means2d = info["means2d"].detach().clone().requires_grad_(True)
    colors = reference_colors({k: v.detach() for k, v in leaves.items()}, 1, info["radii"])
    ref_image, ref_alpha, _ = reference_composite(
        means2d,
        info["conics"].detach(),
        colors,
        info["opacities"].detach(),
        info["radii"],
        info["depths"].detach(),
        scene["width"],
        scene["height"],
        backgrounds=leaves["backgrounds"].detach(),
    )
    torch.testing.assert_close(image.detach(), ref_image.detach(), rtol=1e-9, atol=1e-10)
    per_pixel = (ref_image * w_image).sum(-1) + (ref_alpha * w_alpha).sum(-1)  # [C,H,W]
    (ref_grad,) = torch.autograd.grad(per_pixel.sum(), means2d, retain_graph=True)
    torch.testing.assert_close(grad, ref_grad, rtol=1e-7, atol=1e-9)

    ref_absgrad = torch.zeros_like(means2d)
    flat = per_pixel.reshape(-1)
    for p in range(flat.numel()):
        (g,) = torch.autograd.grad(flat[p], means2d, retain_graph=True)
        ref_absgrad += g.abs()
    torch.testing.assert_close(absgrad, ref_absgrad, rtol=1e-7, atol=1e-9)
    assert (absgrad >= grad.abs() - 1e-12).all() and absgrad.sum() > grad.abs().sum()


def test_info_has_what_splatfacto_and_default_strategy_read():
    scene = make_scene(11, n_cameras=2, sh_degree=3, dtype=torch.float32)
    leaves = _leaves(scene)
    C, N = 2, scene["means"].shape[0]
    image, alpha, info = _fast(leaves, scene, "RGB+ED", absgrad=True, packed=False, sparse_grad=False)
    assert image.shape == (C, scene["height"], scene["width"], 4)
    assert alpha.shape == (C, scene["height"], scene["width"], 1)
    assert info["radii"].shape == (C, N) and info["radii"].dtype == torch.int32
    assert info["means2d"].shape == (C, N, 2) and info["means2d"].requires_grad
    assert info["depths"].shape == (C, N) and info["conics"].shape == (C, N, 3)
    assert info["opacities"].shape == (C, N)
    assert info["gaussian_ids"] is None and info["camera_ids"] is None
    assert (info["width"], info["height"], info["n_cameras"], info["tile_size"]) == (
        scene["width"],
        scene["height"],
        C,
        16,
    )
    assert (info["tile_width"], info["tile_height"]) == (3, 2)
    assert info["isect_offsets"].shape == (C, 2, 3) and info["isect_offsets"].dtype == torch.int32
    assert info["flatten_ids"].dtype == torch.int32 and info["tiles_per_gauss"].dtype == torch.int32
    assert int(info["tiles_per_gauss"].sum()) == info["flatten_ids"].numel() == info["isect_ids"].numel()

    # gsplat's DefaultStrategy: retain_grad before backward, then read grad/absgrad.
    from gsplat.strategy import DefaultStrategy

    params = torch.nn.ParameterDict({"means": torch.nn.Parameter(leaves["means"].detach().clone())})
    strategy = DefaultStrategy(absgrad=True, refine_start_iter=10**9)
    state = strategy.initialize_state()
    strategy.step_pre_backward(params, {}, state, 0, info)
    (image.sum() + alpha.sum()).backward()
    strategy._update_state(params, state, info, packed=False)
    visible = (info["radii"] > 0).any(0)
    assert (state["count"][visible] > 0).all() and (state["count"][~visible] == 0).all()
    assert (state["grad2d"][visible] > 0).any()


def test_nothing_visible_renders_background_with_zero_gradients():
    scene = make_scene(12, n_cameras=1, sh_degree=None)
    leaves = _leaves(scene)
    with torch.no_grad():
        leaves["means"][:, 2] -= 50.0  # everything behind the camera
    image, alpha, info = _fast(leaves, scene, "RGB+ED")
    assert (info["radii"] == 0).all() and info["flatten_ids"].numel() == 0
    assert (alpha == 0).all()
    expected = torch.cat([leaves["backgrounds"][0], torch.zeros(1, dtype=torch.float64)])
    torch.testing.assert_close(image[0], expected.expand_as(image[0]))
    grads = _grads((image, alpha), leaves, [torch.ones_like(image), torch.ones_like(alpha)])
    for name in ("means", "quats", "scales", "opacities", "colors"):
        assert torch.isfinite(grads[name]).all() and (grads[name] == 0).all(), name


def test_gaussian_exactly_at_camera_centre_gives_finite_gradients():
    scene = make_scene(13, n_cameras=1, sh_degree=3)
    leaves = _leaves(scene)
    centre = torch.inverse(scene["viewmats"][0])[:3, 3]
    with torch.no_grad():
        leaves["means"][0] = centre
    image, alpha, info = _fast(leaves, scene)
    assert info["radii"][0, 0] == 0
    grads = _grads((image, alpha), leaves, [torch.ones_like(image), torch.ones_like(alpha)])
    for name, g in grads.items():
        assert torch.isfinite(g).all(), name


def _near_camera_floater_scene(dtype):
    """Floaters a few centimetres in front of the camera over a distant background.

    Modelled on trained scenes whose background Gaussians end up around a held-out camera
    (depths 0.011-0.08 just above near_plane 0.01, opacity logit ~17, projected radii of
    hundreds to thousands of pixels on a small image, centres projected off screen): a blob
    in front of the lens, a thin disc at the near plane, one whose centre projects far
    outside the image (so _persp_proj's clamp of the Jacobian is active), one just inside
    the near plane (culled), one behind the camera, and a background that they hide.
    """
    gen = torch.Generator().manual_seed(77)
    width, height = 64, 48
    Ks = torch.tensor([[61.5, 0.0, 32.0], [0.0, 61.5, 24.0], [0.0, 0.0, 1.0]], dtype=torch.float64)[None]
    viewmat = _look_at_viewmat((0.3, -0.2, -2.0), (0.0, 0.0, 0.0))
    n_back = 24
    cam_means = torch.cat(
        [
            torch.tensor(
                [
                    [0.005, -0.003, 0.04],  # blob in front of the lens
                    [0.002, 0.001, 0.0115],  # thin disc at the near plane
                    [0.012, 0.002, 0.011],  # centre projects to x ~ 99 px of 64
                    [0.0, 0.0, 0.0099],  # inside the near plane: culled
                    [0.0, 0.0, -0.5],  # behind the camera
                ],
                dtype=torch.float64,
            ),
            (torch.rand(n_back, 3, generator=gen, dtype=torch.float64) - 0.5) * torch.tensor([1.6, 1.2, 1.0])
            + torch.tensor([0.0, 0.0, 2.0]),
        ]
    )
    cam_to_world = torch.inverse(viewmat)
    means = cam_means @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]
    n = means.shape[0]
    quats = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    scales = torch.cat(
        [
            torch.tensor(
                [[0.03, 0.03, 0.03], [1.5e-4, 0.1, 0.016], [0.004, 0.03, 0.01], [0.05, 0.05, 0.05], [0.3, 0.3, 0.3]],
                dtype=torch.float64,
            ),
            torch.exp(torch.randn(n_back, 3, generator=gen, dtype=torch.float64) * 0.4) * 0.12,
        ]
    )
    opacities = torch.sigmoid(torch.full((n,), 17.23, dtype=torch.float64))
    opacities[5:] = 0.6 + 0.39 * torch.rand(n_back, generator=gen, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    scene = dict(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=colors,
        viewmats=viewmat[None],
        Ks=Ks,
        backgrounds=torch.zeros(1, 3, dtype=torch.float64),
    )
    scene = {k: v.to(dtype) for k, v in scene.items()}
    scene.update(width=width, height=height, sh_degree=None)
    return scene


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["float32", "float64"])
def test_near_camera_floaters_match_gsplat_reference(dtype):
    """Gaussians just beyond the near plane with radii far beyond the image: projection and
    tile lists as gsplat's own _torch_impl, compositing as the kernel's per-pixel rule."""
    scene = _near_camera_floater_scene(dtype)
    width, height = scene["width"], scene["height"]
    leaves = _leaves(scene, names=())
    ref_radii, ref_means2d, ref_depths, ref_conics, _ = reference_project(leaves, width, height)
    image, alpha, info = _fast(leaves, scene, use_background=False)

    # the condition is there: near floaters visible with huge radii, one centre off screen,
    # the one inside the near plane and the one behind the camera culled
    radii = info["radii"][0]
    assert radii[:3].min() > 2 * width and radii.max() > 20 * width
    assert info["means2d"][0, 2, 0] > width
    assert radii[3] == 0 and radii[4] == 0
    assert (radii[5:] > 0).sum() > 10

    assert torch.equal(info["radii"], ref_radii.to(torch.int32))
    visible = ref_radii > 0
    rtol = 1e-6 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(info["means2d"][visible], ref_means2d[visible], rtol=rtol, atol=0.0)
    torch.testing.assert_close(info["conics"][visible], ref_conics[visible], rtol=rtol, atol=0.0)
    torch.testing.assert_close(info["depths"], ref_depths, rtol=rtol, atol=0.0)

    tile_width, tile_height = math.ceil(width / 16), math.ceil(height / 16)
    ref_tpg, ref_ids, ref_flat = _isect_tiles(ref_means2d, ref_radii, ref_depths, 16, tile_width, tile_height)
    assert torch.equal(info["tiles_per_gauss"], ref_tpg)
    assert torch.equal(info["flatten_ids"], ref_flat)
    assert torch.equal(info["isect_offsets"], _isect_offset_encode(ref_ids, 1, tile_width, tile_height))

    opacities = leaves["opacities"][None].expand_as(ref_depths)
    ref_image, ref_alpha, chosen = reference_composite(
        ref_means2d, ref_conics, leaves["colors"][None], opacities, ref_radii, ref_depths, width, height
    )
    tol = dict(rtol=1e-5, atol=1e-6) if dtype == torch.float32 else dict(rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(image, ref_image, **tol)
    torch.testing.assert_close(alpha, ref_alpha, **tol)
    # the floaters are what the camera sees: the first Gaussian of nearly every pixel is one
    # of them and the background is hidden wherever they reach the 1e-4 stop
    first = torch.tensor([ch[0] if ch else -1 for ch in chosen[0]])
    assert ((first >= 0) & (first < 3)).float().mean() > 0.95


# ---------------------------------------------------------------------------------------
# tests: tile intersection lists
# ---------------------------------------------------------------------------------------


def _projected(seed, n_cameras, width, height, dtype=torch.float32):
    scene = make_scene(seed, n_gaussians=120, n_cameras=n_cameras, width=width, height=height, dtype=dtype)
    with torch.no_grad():
        radii, means2d, depths, conics, _ = project_gaussians_torch(
            scene["means"], scene["quats"], scene["scales"], scene["viewmats"], scene["Ks"], width, height
        )
    return radii, means2d, depths


@pytest.mark.parametrize("tile_size,width,height", [(16, 37, 29), (8, 50, 21), (4, 13, 9)])
def test_isect_tiles_matches_simple_reference(tile_size, width, height):
    radii, means2d, depths = _projected(20 + tile_size, 3, width, height)
    C, N = radii.shape
    tile_width, tile_height = math.ceil(width / tile_size), math.ceil(height / tile_size)
    tiles_per_gauss, offsets, flatten_ids = isect_tiles_torch(
        means2d, radii, depths, tile_size, tile_width, tile_height
    )

    pairs: List[Tuple[int, int, float, int]] = []
    expected_counts = torch.zeros(C, N, dtype=torch.int32)
    for cam in range(C):
        for i in range(N):
            if radii[cam, i] <= 0:
                continue
            mx, my = means2d[cam, i].tolist()
            for ty in range(tile_height):
                for tx in range(tile_width):
                    if _in_tile_box(mx, my, int(radii[cam, i]), tx, ty, tile_size, tile_width, tile_height):
                        pairs.append((cam, ty * tile_width + tx, float(depths[cam, i]), cam * N + i))
                        expected_counts[cam, i] += 1
    pairs.sort()
    assert torch.equal(tiles_per_gauss, expected_counts)
    assert flatten_ids.dtype == torch.int32 and offsets.dtype == torch.int32
    assert flatten_ids.tolist() == [p[3] for p in pairs]
    keys = [p[0] * tile_width * tile_height + p[1] for p in pairs]
    expected_offsets = [sum(1 for k in keys if k < t) for t in range(C * tile_width * tile_height)]
    assert offsets.reshape(-1).tolist() == expected_offsets
    # every tile's run, read the way consumers read it, is its Gaussians front to back
    flat = offsets.reshape(-1).tolist() + [flatten_ids.numel()]
    for t in range(C * tile_width * tile_height):
        run = flatten_ids[flat[t] : flat[t + 1]].long()
        run_depths = depths.reshape(-1)[run]
        assert (run_depths[1:] >= run_depths[:-1]).all()
        assert ((run // N) == t // (tile_width * tile_height)).all()


def test_isect_tiles_matches_gsplat_torch_reference():
    """gsplat's own pure-torch isect_tiles/isect_offset_encode, including isect_ids."""
    from votesplat_ns.core.rasterize_torch import _isect_tiles_with_ids

    width, height, tile_size = 45, 30, 16
    radii, means2d, depths = _projected(30, 2, width, height)
    tile_width, tile_height = math.ceil(width / tile_size), math.ceil(height / tile_size)
    ref_tpg, ref_ids, ref_flat = _isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height)
    ref_offsets = _isect_offset_encode(ref_ids, 2, tile_width, tile_height)
    tpg, offsets, flat, ids = _isect_tiles_with_ids(means2d, radii, depths, tile_size, tile_width, tile_height)
    assert torch.equal(tpg, ref_tpg)
    assert torch.equal(ids, ref_ids)
    assert torch.equal(flat, ref_flat)
    assert torch.equal(offsets, ref_offsets)


def test_isect_tiles_empty():
    radii = torch.zeros(2, 5, dtype=torch.int32)
    tpg, offsets, flat = isect_tiles_torch(torch.zeros(2, 5, 2), radii, torch.ones(2, 5), 16, 3, 2)
    assert (tpg == 0).all() and flat.numel() == 0 and offsets.shape == (2, 2, 3) and (offsets == 0).all()


# ---------------------------------------------------------------------------------------
# tests: input checking
# ---------------------------------------------------------------------------------------


def test_bad_input_raises_clear_errors():
    scene = make_scene(14, n_cameras=1, sh_degree=3, dtype=torch.float32)
    leaves = _leaves(scene, names=())
    with pytest.raises(ValueError, match="packed=False"):
        _fast(leaves, scene, packed=True)
    with pytest.raises(ValueError, match="render_mode"):
        _fast(leaves, scene, render_mode="RGBD")
    with pytest.raises(ValueError, match="sh_degree"):
        rasterize_torch(
            *(leaves[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")),
            37,
            29,
            sh_degree=4,
        )
    with pytest.raises(ValueError, match="camera_model"):
        _fast(leaves, scene, camera_model="fisheye")
    with pytest.raises(TypeError, match="bogus"):
        _fast(leaves, scene, bogus=1)
    bad = dict(leaves)
    bad["means"] = leaves["means"].clone()
    bad["means"][3, 1] = float("nan")
    with pytest.raises(ValueError, match="means contains NaN"):
        _fast(bad, scene)
    bad = dict(leaves)
    bad["opacities"] = leaves["opacities"][:-1]
    with pytest.raises(ValueError, match=r"opacities must be \[N\]"):
        _fast(bad, scene)


# ---------------------------------------------------------------------------------------
# GPU: the same code on CUDA, and against gsplat's CUDA rasterizer
# ---------------------------------------------------------------------------------------


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU to compare against gsplat's CUDA kernels")
def test_cuda_matches_cpu_and_gsplat():
    scene = make_scene(15, n_gaussians=400, n_cameras=2, width=70, height=45, sh_degree=3, dtype=torch.float32)
    cpu_leaves = _leaves(scene)
    cuda_leaves = {k: v.detach().cuda().requires_grad_(v.requires_grad) for k, v in cpu_leaves.items()}
    cpu = _fast(cpu_leaves, scene, "RGB+ED", absgrad=True)
    gpu = _fast(cuda_leaves, scene, "RGB+ED", absgrad=True)
    torch.testing.assert_close(gpu[0].cpu(), cpu[0], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(gpu[1].cpu(), cpu[1], rtol=1e-4, atol=1e-4)
    assert torch.equal(gpu[2]["flatten_ids"].cpu(), cpu[2]["flatten_ids"])

    from gsplat.rendering import rasterization

    gs_leaves = {k: v.detach().cuda().requires_grad_(v.requires_grad) for k, v in cpu_leaves.items()}
    ref = rasterization(
        gs_leaves["means"],
        gs_leaves["quats"],
        gs_leaves["scales"],
        gs_leaves["opacities"],
        gs_leaves["colors"],
        gs_leaves["viewmats"],
        gs_leaves["Ks"],
        scene["width"],
        scene["height"],
        sh_degree=3,
        packed=False,
        backgrounds=gs_leaves["backgrounds"],
        render_mode="RGB+ED",
        absgrad=True,
    )
    torch.testing.assert_close(gpu[0], ref[0], rtol=1e-3, atol=1e-3)
    torch.testing.assert_close(gpu[1], ref[1], rtol=1e-3, atol=1e-3)
    for key in ("radii", "tiles_per_gauss", "isect_offsets", "flatten_ids"):
        assert torch.equal(gpu[2][key], ref[2][key].to(gpu[2][key].dtype)), key
    # isect_ids: same camera|tile bits; the depth bits may differ by float rounding (ulps)
    assert torch.equal(gpu[2]["isect_ids"] >> 32, ref[2]["isect_ids"] >> 32)
    assert ((gpu[2]["isect_ids"] & 0xFFFFFFFF) - (ref[2]["isect_ids"] & 0xFFFFFFFF)).abs().max() <= 8
    weights = [torch.randn_like(ref[0]), torch.randn_like(ref[1])]
    fast_grads = _grads(gpu[:2], cuda_leaves, weights)
    ref_grads = _grads(ref[:2], gs_leaves, weights)
    for name in ("means", "quats", "scales", "opacities", "colors", "backgrounds"):
        scale = ref_grads[name].abs().max().clamp(min=1e-6)
        assert ((fast_grads[name] - ref_grads[name]).abs().max() / scale) < 1e-3, name
