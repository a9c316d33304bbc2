"""Retrofit from a standard 3DGS PLY: which frame its Gaussians are in, and moving them into the training frame.

A PLY's x, y, z can be in one of three frames of a nerfstudio capture:

- ``dataparser``: the normalised frame nerfstudio trains in (its dataparser's orientation, centring
  and scale applied). ``ns-export gaussian-splat`` and votesplat's own export write this frame.
- ``dataset``: the frame of the poses in transforms.json.
- ``colmap``: the frame before transforms.json's ``applied_transform``: COLMAP's world for a capture
  that ns-process-data made from COLMAP (the original 3DGS, and gsplat's simple_trainer with
  ``--no-normalize-world-space``, write PLYs in it). Without an applied_transform it is ``dataset``.

Each frame reaches the training frame by a similarity p' = s (A p + b) built from nerfstudio's
``dataparser_transform``, ``dataparser_scale`` and transforms.json's applied_transform/applied_scale
(:func:`frames_from_dataparser`). It moves each Gaussian rigidly: means as points, log scales
+ log s, rotations composed with A, and the SH colour bands rotated, so the scene renders the
same from the moved cameras.

Which frame a file is in is checked against the training views, never assumed:
:func:`resolve_frame` moves the Gaussians into every candidate frame, counts the share whose
centre projects into at least one training view, and renders a few training views to compare
with the photos (PSNR). A frame must put at least ``MIN_IN_VIEW_SHARE`` of the Gaussians in
view and render best by ``PSNR_MARGIN_DB``; otherwise the retrofit stops with one line saying
which ``--pipeline.model.retrofit-frame`` to pass. The in-view share alone cannot tell frames
apart: shrinking a 360° scene towards the point the cameras look at keeps it in view.

No nerfstudio import at module level: this is torch maths plus one function that reads a
nerfstudio datamanager (:func:`retrofit_reference`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor

from votesplat_ns.core.cameras import PinholeView, scaled_view
from votesplat_ns.errors import VoteSplatInputError
from votesplat_ns.ns.run import camera_view

FRAMES = ("dataparser", "dataset", "colmap")
"""The frames a retrofit PLY can be in, in the order they are preferred when they coincide."""

MIN_IN_VIEW_SHARE = 0.5
"""A frame must put at least this share of the Gaussian centres inside some training view."""

IN_VIEW_SAMPLE = 1 << 18
"""The share is measured on an even sample of at most about this many Gaussians (within 0.3 points, 3 sigma)."""

PSNR_MARGIN_DB = 3.0
"""The chosen frame must render the training views better than any other candidate by this much."""

PHOTO_VIEWS = 4
"""Training views rendered to compare frames (spread over the capture)."""

PHOTO_MAX_WIDTH = 64
"""Width in pixels at which those views are rendered: enough to tell a wrong frame, cheap on a CPU."""

SAME_FRAME_TOLERANCE = 1e-3
"""Two frames are the same when they place every Gaussian within this share of the cameras' extent."""

# nerfstudio's dataparser uses this applied_transform for COLMAP captures whose transforms.json predates the field
_LEGACY_COLMAP_APPLIED_TRANSFORM = [[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0]]


# ----------------------------------------------------------------------------------------
# rigid motion of Gaussians (pure torch)
# ----------------------------------------------------------------------------------------


def homogeneous(matrix: Tensor) -> Tensor:
    """[3, 4] or [4, 4] -> [4, 4] float64 on the CPU."""
    matrix = torch.as_tensor(matrix).detach().to("cpu", torch.float64)
    if matrix.shape == (4, 4):
        return matrix.clone()
    out = torch.eye(4, dtype=torch.float64)
    out[:3] = matrix
    return out


def similarity_parts(matrix: Tensor) -> Tuple[float, Tensor, Tensor]:
    """Split p -> M p (M [4, 4], on the CPU) into scale s, rotation R [3, 3] and translation t with M p = s R p + t.

    Raises ValueError when M is not a similarity (shear, anisotropic scale or a mirror).
    """
    matrix = homogeneous(matrix)
    linear = matrix[:3, :3]
    det = float(torch.linalg.det(linear))
    if not det > 0:
        raise ValueError(f"the frame transform mirrors or collapses space (det {det:.3g})")
    scale = det ** (1.0 / 3.0)
    rotation = linear / scale
    error = float((rotation @ rotation.T - torch.eye(3, dtype=torch.float64)).abs().max())
    if error > 1e-4:
        raise ValueError(f"the frame transform is not a rotation and uniform scale (orthogonality error {error:.2g})")
    return scale, rotation, matrix[:3, 3].clone()


def rotation_to_quaternion(rotation: Tensor) -> Tensor:
    """Rotation matrix [3, 3] -> unit quaternion [4] (w, x, y, z), w >= 0."""
    m = torch.as_tensor(rotation, dtype=torch.float64)
    trace = float(m[0, 0] + m[1, 1] + m[2, 2])
    # Shepperd: divide by the largest of 4w^2, 4x^2, 4y^2, 4z^2 for accuracy
    candidates = [trace, float(m[0, 0]), float(m[1, 1]), float(m[2, 2])]
    k = max(range(4), key=lambda i: candidates[i])
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif k == 1:
        s = 2.0 * math.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 1e-300))
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(max(1.0 - m[0, 0] + m[1, 1] - m[2, 2], 1e-300))
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(max(1.0 - m[0, 0] - m[1, 1] + m[2, 2], 1e-300))
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    quat = torch.tensor([float(v) for v in q], dtype=torch.float64)
    quat = quat / quat.norm()
    return quat if quat[0] >= 0 else -quat


def quaternion_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a * b of (w, x, y, z) quaternions, broadcast over leading dimensions."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def _fibonacci_directions(count: int) -> Tensor:
    index = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * index / count
    radius = torch.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * index
    return torch.stack([radius * torch.cos(phi), radius * torch.sin(phi), z], dim=-1)


def sh_rotation_matrices(rotation: Tensor, degree: int) -> List[Tensor]:
    """Per SH band l = 1..degree, the [2l+1, 2l+1] matrix D_l with f'_l = D_l f_l for a scene rotated by ``rotation``.

    In gsplat's real SH basis Y (the renderer's), the rotated scene must show colour c'(d) = c(R^T d)
    in direction d. Each band is closed under rotation, so D_l solves Y_l(d) D_l = Y_l(R^T d) exactly
    on any set of directions that spans it (least squares on a Fibonacci sphere).
    """
    from gsplat.cuda._torch_impl import _eval_sh_bases_fast  # gsplat's exact basis (torch, no CUDA)

    rotation = torch.as_tensor(rotation, dtype=torch.float64)
    num_bases = (degree + 1) ** 2
    directions = _fibonacci_directions(64)
    bases = _eval_sh_bases_fast(num_bases, directions)
    rotated = _eval_sh_bases_fast(num_bases, directions @ rotation)  # rows: (R^T d)^T = d^T R
    matrices = []
    for band in range(1, degree + 1):
        cols = slice(band * band, (band + 1) * (band + 1))
        matrices.append(torch.linalg.lstsq(bases[:, cols], rotated[:, cols]).solution)
    return matrices


def rotate_sh(features_rest: Tensor, rotation: Tensor) -> Tensor:
    """SH coefficients of degree >= 1, [N, K, 3] (K = (d+1)^2 - 1), for the scene rotated by ``rotation``."""
    num_rest = features_rest.shape[1]
    degree = int(round(math.sqrt(num_rest + 1))) - 1
    if (degree + 1) ** 2 - 1 != num_rest:
        raise ValueError(f"features_rest has {num_rest} coefficients per channel, which is no SH degree")
    if degree == 0:
        return features_rest.clone()
    out = torch.empty_like(features_rest)
    for band, matrix in enumerate(sh_rotation_matrices(rotation, degree), start=1):
        rows = slice(band * band - 1, (band + 1) * (band + 1) - 1)
        # c(d) = sum_k Y_k(d) f_k per channel, so f' = D f on each band
        out[:, rows] = torch.einsum("ij,njc->nic", matrix.to(features_rest), features_rest[:, rows])
    return out


def transform_means(means: Tensor, matrix: Tensor) -> Tensor:
    """Points [N, 3] moved by the similarity p -> M p (M [4, 4] or [3, 4]), in float64, returned in ``means``' dtype:
    the means of :func:`transform_gaussians`, without the rest of the Gaussians."""
    scale, rotation, translation = similarity_parts(torch.as_tensor(matrix).cpu())
    return (scale * means.double() @ rotation.T.to(means.device) + translation.to(means.device)).to(means)


def transform_gaussians(
    gaussians: Dict[str, Tensor], matrix: Tensor, moved_means: Optional[Tensor] = None
) -> Dict[str, Tensor]:
    """splatfacto's Gaussian parameters moved by the similarity p -> M p (M [4, 4] or [3, 4]).

    means: M p; scales (log): + log s; quats (w, x, y, z, not normalised): q_R * q, keeping their
    norm; features_rest: each SH band rotated; features_dc and opacities unchanged. ``moved_means``: the
    means' :func:`transform_means` by ``matrix`` when the caller has them already.
    """
    scale, rotation, _ = similarity_parts(torch.as_tensor(matrix).cpu())
    moved = dict(gaussians)
    moved["means"] = transform_means(gaussians["means"], matrix) if moved_means is None else moved_means
    moved["scales"] = gaussians["scales"] + math.log(scale)
    quats = gaussians["quats"]
    turn = rotation_to_quaternion(rotation).to(quats.device)
    moved["quats"] = quaternion_multiply(turn.expand_as(quats), quats.double()).to(quats)
    moved["features_rest"] = rotate_sh(gaussians["features_rest"], rotation)
    return moved


# ----------------------------------------------------------------------------------------
# how well a frame fits the training views
# ----------------------------------------------------------------------------------------


def in_view(means: Tensor, views: Sequence[PinholeView], near: float = 0.01, chunk: int = 1 << 18) -> Tensor:
    """[N] bool: the centre is in front of (depth > ``near``) and inside the image of at least one view."""
    seen = torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
    for view in views:
        viewmat = view.viewmat.to(means)
        K = view.K.to(means)
        for start in range(0, means.shape[0], chunk):
            block = means[start : start + chunk]
            cam = block @ viewmat[:3, :3].T + viewmat[:3, 3]
            depth = cam[:, 2]
            pix = cam @ K.T
            u = pix[:, 0] / depth.clamp(min=near)
            v = pix[:, 1] / depth.clamp(min=near)
            inside = (depth > near) & (u >= 0) & (u < view.width) & (v >= 0) & (v < view.height)
            seen[start : start + chunk] |= inside
    return seen


def render_psnr(
    gaussians: Dict[str, Tensor], views: Sequence[PinholeView], rasterize_fn: Callable, sh_degree: int
) -> float:
    """Mean PSNR (dB) of the Gaussians rendered over black against each view's ``image`` [H, W, 3] in [0, 1]."""
    means = gaussians["means"]
    quats = gaussians["quats"] / gaussians["quats"].norm(dim=-1, keepdim=True)
    colors = torch.cat([gaussians["features_dc"][:, None, :], gaussians["features_rest"]], dim=1)
    opacities = torch.sigmoid(gaussians["opacities"]).reshape(-1)
    scores = []
    for view in views:
        if view.image is None:
            raise ValueError("render_psnr compares renders with the views' images; pass views that have one")
        render, _, _ = rasterize_fn(
            means,
            quats,
            torch.exp(gaussians["scales"]),
            opacities,
            colors,
            view.viewmat[None].to(means),
            view.K[None].to(means),
            view.width,
            view.height,
            sh_degree=sh_degree,
        )
        mse = float(((render[0].clamp(0, 1) - view.image.to(means)) ** 2).mean())
        scores.append(-10.0 * math.log10(max(mse, 1e-10)))
    return sum(scores) / len(scores)


@dataclass
class FrameFit:
    """How the Gaussians of a file fit the training views when read in one frame."""

    name: str
    same_as: List[str]  # other frame names that place the Gaussians (almost) identically
    in_view_share: float
    psnr: Optional[float]  # None when too few Gaussians are in view to bother rendering

    def label(self) -> str:
        return "/".join([self.name] + self.same_as)


class RetrofitReference:
    """What a retrofit from a PLY needs from the capture: the frames, and the training views.

    ``frames`` maps each frame name to the [4, 4] transform into the training (dataparser) frame;
    ``views()`` returns (every training view, without image; a few views with their photo at
    ``PHOTO_MAX_WIDTH``), loaded by ``load_views`` on first use.
    """

    def __init__(
        self,
        frames: Dict[str, Tensor],
        load_views: Callable[[], Tuple[List[PinholeView], List[PinholeView]]],
        test_mode: str = "val",
    ):
        self.frames = frames
        self.test_mode = test_mode
        self._load_views = load_views
        self._views: Optional[Tuple[List[PinholeView], List[PinholeView]]] = None

    def views(self) -> Tuple[List[PinholeView], List[PinholeView]]:
        if self._views is None:
            self._views = self._load_views()
        return self._views


def resolve_frame(
    gaussians: Dict[str, Tensor],
    reference: RetrofitReference,
    requested: str,
    source: Path,
    rasterize_fn: Callable,
    sh_degree: int,
) -> Tuple[str, Dict[str, Tensor], List[FrameFit]]:
    """Move a file's Gaussians into the training frame from the ``requested`` frame ('auto': the one that fits).

    Returns (frame name, moved Gaussians, the fit of every candidate). Raises
    :class:`VoteSplatInputError` (one line, what to pass) when the requested frame puts fewer than
    ``MIN_IN_VIEW_SHARE`` of the Gaussians in view or another frame renders the views clearly better,
    and, for 'auto', when no frame fits or two different frames fit equally well.
    """
    if requested != "auto" and requested not in reference.frames:
        raise VoteSplatInputError(
            f"--pipeline.model.retrofit-frame {requested}: unknown frame; use auto or one of {', '.join(reference.frames)}"
        )
    all_views, photo_views = reference.views()
    device = gaussians["means"].device
    centres = torch.stack([torch.inverse(view.viewmat.double())[:3, 3] for view in all_views])
    extent = max(float((centres - centres.mean(0)).norm(dim=-1).max()), 1e-6)
    count = gaussians["means"].shape[0]
    probe = gaussians["means"][torch.linspace(0, count - 1, min(4096, count)).long().to(device)]

    fits: List[FrameFit] = []
    moved: Dict[str, Dict[str, Tensor]] = {}
    moved_means: Dict[str, Tensor] = {}
    probes: Dict[str, Tensor] = {}
    for name in [n for n in FRAMES if n in reference.frames]:
        matrix = reference.frames[name]
        try:
            scale, rotation, translation = similarity_parts(matrix)
        except ValueError as err:
            if requested == name:
                raise VoteSplatInputError(f"--pipeline.model.retrofit-frame {name}: {err}; use another frame") from None
            continue
        placed = scale * probe.double() @ rotation.T.to(device) + translation.to(device)
        twin = next(
            (
                fit
                for fit in fits
                if float((probes[fit.name] - placed).norm(dim=-1).max()) <= SAME_FRAME_TOLERANCE * extent
            ),
            None,
        )
        if twin is not None:
            twin.same_as.append(name)
            continue
        probes[name] = placed
        moved_means[name] = transform_means(gaussians["means"], matrix)
        # an even sample: a retrofit of millions of Gaussians does not project each one into every training view
        sample = moved_means[name][:: max(1, count // IN_VIEW_SAMPLE)]
        share = float(in_view(sample, all_views).float().mean())
        fits.append(FrameFit(name, [], share, None))
    for fit in fits:
        if fit.in_view_share >= MIN_IN_VIEW_SHARE:
            # only the frames rendered here can be chosen: the others' SH bands are never rotated
            moved[fit.name] = transform_gaussians(gaussians, reference.frames[fit.name], moved_means.pop(fit.name))
            fit.psnr = render_psnr(moved[fit.name], photo_views, rasterize_fn, sh_degree)

    def summary() -> str:
        return ", ".join(
            f"{fit.label()}: {fit.in_view_share:.1%} in view" + (f", {fit.psnr:.1f} dB" if fit.psnr is not None else "")
            for fit in fits
        )

    # the frames whose renders were scored, best first, and their PSNRs
    scored = sorted(((fit.psnr, fit) for fit in fits if fit.psnr is not None), key=lambda pair: -pair[0])
    fitting, psnrs = [fit for _, fit in scored], [psnr for psnr, _ in scored]
    frame_flag = "--pipeline.model.retrofit-frame"
    if requested != "auto":
        chosen = next(fit for fit in fits if requested == fit.name or requested in fit.same_as)
        if chosen.psnr is None:
            better = (
                f"pass {frame_flag} {fitting[0].name}"
                if fitting
                else "check that the PLY is a scene of this capture (--data)"
            )
            raise VoteSplatInputError(
                f"only {chosen.in_view_share:.1%} of the Gaussians of {source} project into the training views in frame "
                f"'{requested}' ({summary()}); {better}"
            )
        best = fitting[0]
        if best is not chosen and psnrs[0] >= chosen.psnr + PSNR_MARGIN_DB:
            raise VoteSplatInputError(
                f"{source} is not in frame '{requested}': it renders the training views at {chosen.psnr:.1f} dB PSNR in it and at "
                f"{psnrs[0]:.1f} dB in frame '{best.name}' ({summary()}); pass {frame_flag} {best.name}"
            )
        return requested, moved[chosen.name], fits
    if not fitting:
        best_share = max(fits, key=lambda fit: fit.in_view_share)
        raise VoteSplatInputError(
            f"only {best_share.in_view_share:.1%} of the Gaussians of {source} project into the training views in any frame "
            f"({summary()}); check that the PLY is a scene of this capture (--data), in the capture's own frame "
            f"(gsplat's simple_trainer: train with --no-normalize-world-space)"
        )
    if len(fitting) > 1 and psnrs[0] < psnrs[1] + PSNR_MARGIN_DB:
        a, b = fitting[0].name, fitting[1].name
        raise VoteSplatInputError(
            f"cannot tell the frame of {source}: frames '{a}' and '{b}' both fit the training views ({summary()}); "
            f"pass {frame_flag} {a} or {frame_flag} {b}"
        )
    return fitting[0].name, moved[fitting[0].name], fits


# ----------------------------------------------------------------------------------------
# the capture's frames and views, from a nerfstudio datamanager
# ----------------------------------------------------------------------------------------


def applied_transform_of(data: Path) -> Tuple[Optional[Tensor], float]:
    """transforms.json's applied_transform [3, 4] (None: there is none) and applied_scale, as nerfstudio's dataparser takes them."""
    data = Path(data)
    transforms = data if data.suffix == ".json" else data / "transforms.json"
    meta = json.loads(transforms.read_text()) if transforms.is_file() else {}
    scale = float(meta.get("applied_scale", 1.0))
    if "applied_transform" in meta:
        return torch.tensor(meta["applied_transform"], dtype=torch.float64), scale
    if (data / "colmap" / "sparse" / "0").exists():
        return torch.tensor(_LEGACY_COLMAP_APPLIED_TRANSFORM, dtype=torch.float64), scale
    return None, scale


def frames_from_dataparser(
    dataparser_transform: Tensor,
    dataparser_scale: float,
    applied_transform: Optional[Tensor],
    applied_scale: float = 1.0,
) -> Dict[str, Tensor]:
    """[4, 4] transforms into the training frame of the frames 'dataparser' (identity), 'dataset' and 'colmap'.

    nerfstudio's dataparser maps transforms.json's poses by s (T p) with T = dataparser_transform
    applied_transform^-1 and s = dataparser_scale / applied_scale (it reports the product with
    applied_scale), and ns-process-data made those poses as applied_scale (A p) from the original
    (COLMAP) frame, as nerfstudio's ``transform_poses_to_original_space`` undoes them.
    """
    applied = homogeneous(applied_transform) if applied_transform is not None else torch.eye(4, dtype=torch.float64)
    transform = homogeneous(dataparser_transform) @ torch.linalg.inv(applied)
    auto_scale = dataparser_scale / applied_scale
    dataset = torch.diag(torch.tensor([auto_scale] * 3 + [1.0], dtype=torch.float64)) @ transform
    colmap = dataset @ torch.diag(torch.tensor([applied_scale] * 3 + [1.0], dtype=torch.float64)) @ applied
    return {"dataparser": torch.eye(4, dtype=torch.float64), "dataset": dataset, "colmap": colmap}


def _photo(image: Tensor, view: PinholeView) -> Tensor:
    image = image[..., :3]
    image = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
    if image.shape[:2] != (view.height, view.width):
        image = F.interpolate(image.permute(2, 0, 1)[None], size=(view.height, view.width), mode="area")[0].permute(
            1, 2, 0
        )
    return image.cpu()


def retrofit_reference(datamanager) -> RetrofitReference:
    """The frames and training views of a nerfstudio full-image datamanager (votesplat's), for :func:`resolve_frame`."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    outputs = datamanager.train_dataparser_outputs
    applied, applied_scale = None, 1.0
    if isinstance(datamanager.config.dataparser, NerfstudioDataParserConfig):
        applied, applied_scale = applied_transform_of(Path(datamanager.config.dataparser.data))
    frames = frames_from_dataparser(
        outputs.dataparser_transform, float(outputs.dataparser_scale), applied, applied_scale
    )

    def views() -> Tuple[List[PinholeView], List[PinholeView]]:
        cached = datamanager.cached_train  # undistorts the images and updates the cameras to match; do it first
        cameras = datamanager.train_dataset.cameras
        every = [camera_view(cameras.to("cpu"), i, str(i), dtype=torch.float64) for i in range(cameras.shape[0])]
        picks = sorted(
            {int(round(x)) for x in torch.linspace(0, len(every) - 1, min(PHOTO_VIEWS, len(every))).tolist()}
        )
        photos = []
        for i in picks:
            view = scaled_view(every[i], max_width=PHOTO_MAX_WIDTH)
            view = replace(view, viewmat=view.viewmat.float(), K=view.K.float())
            photos.append(replace(view, image=_photo(cached[i]["image"], view)))
        return every, photos

    return RetrofitReference(frames, views, test_mode=getattr(datamanager, "test_mode", "val"))
