"""The one camera record the export, query and viewer code pass around (pure torch, no nerfstudio).

gsplat's conventions: world-to-camera ``viewmat`` [4, 4] with OpenCV axes (x right, y down,
z forward), intrinsics ``K`` [3, 3] in the continuous pixel frame (pixel centre = index + 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Optional

import torch


@dataclass
class PinholeView:
    """One pinhole camera and, where the caller has them, its image's name and picture."""

    viewmat: torch.Tensor  # [4, 4] world-to-camera, OpenCV axes
    K: torch.Tensor  # [3, 3]
    width: int
    height: int
    name: str = ""  # the image file it was taken from (queries name views by it)
    image: Optional[torch.Tensor] = None  # [H, W, 3] in [0, 1] (export draws it above the id map)


def viewmat_from_camera_to_world(camera_to_world: torch.Tensor) -> torch.Tensor:
    """nerfstudio camera-to-world [3, 4] (OpenGL axes) -> gsplat world-to-camera [4, 4] (OpenCV).

    The same conversion as splatfacto's ``get_viewmat``.
    """
    rotation = camera_to_world[:3, :3] * torch.tensor(
        [1.0, -1.0, -1.0], dtype=camera_to_world.dtype, device=camera_to_world.device
    )
    translation = camera_to_world[:3, 3:4]
    viewmat = torch.eye(4, dtype=camera_to_world.dtype, device=camera_to_world.device)
    viewmat[:3, :3] = rotation.T
    viewmat[:3, 3:4] = -rotation.T @ translation
    return viewmat


def scaled_view(
    view: PinholeView, max_width: Optional[int] = None, width: Optional[int] = None, height: Optional[int] = None
) -> PinholeView:
    """``view`` at another resolution: at most ``max_width`` wide, or exactly ``width`` x ``height``.

    Intrinsics scale with the image in the continuous pixel frame (pixel centre = index + 0.5).
    A picture the view carries is dropped when the size changes (it would no longer match).
    """
    if width is None or height is None:
        if max_width is None or view.width <= max_width:
            return view
        if max_width < 1:
            raise ValueError(f"max_width must be >= 1, got {max_width}")
        scale = max_width / view.width
        width, height = max(1, int(round(view.width * scale))), max(1, int(round(view.height * scale)))
    if (width, height) == (view.width, view.height):
        return view
    sx, sy = width / view.width, height / view.height
    if abs(sx - sy) > 0.02 * max(sx, sy):
        raise ValueError(
            f"cannot render {view.name or 'the view'} ({view.width}x{view.height}) at {width}x{height}: "
            "the aspect ratio differs; the labels must be made at the image's aspect ratio"
        )
    K = view.K.clone()
    K[0] *= sx
    K[1] *= sy
    return replace(view, K=K, width=int(width), height=int(height), image=None)
