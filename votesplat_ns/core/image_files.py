"""Image and label files as the plugin reads them: decoded in full, with errors that name the file."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Sequence, Tuple, Union

import numpy as np
from PIL import Image, UnidentifiedImageError

from votesplat_ns.errors import VoteSplatInputError

PathLike = Union[str, Path]


def file_digest(path: PathLike, chunk_size: int = 1 << 20) -> str:
    """sha256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while True:
            chunk = handle.read(chunk_size)
            if not chunk:
                break
            digest.update(chunk)
    return digest.hexdigest()


def load_image_file(path: PathLike, what: str = "image") -> Image.Image:
    """An image file decoded in full by PIL; a missing, truncated or unreadable file raises a
    :class:`VoteSplatInputError` naming it (``what``: "image", "label image", ...).

    Every image and label file the plugin reads goes through here (nerfstudio's own image loading
    is checked with it too, see the datamanager), so a broken file is always named.
    """
    path = Path(path)
    if not path.is_file():
        raise VoteSplatInputError(f"{what} {path} does not exist")
    if path.stat().st_size == 0:
        raise VoteSplatInputError(f"{what} {path} is empty (0 bytes); replace it with an intact file")
    try:
        with Image.open(path) as image:
            image.load()
    except PermissionError as error:
        raise VoteSplatInputError(
            f"{what} {path} cannot be read ({error.strerror}); make it readable (e.g. chmod a+r)"
        ) from None
    except Exception as error:  # PIL raises OSError, ValueError, SyntaxError, ... for broken files
        text = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        if isinstance(error, UnidentifiedImageError):
            text = "not an image format PIL can read"
        elif "truncated" in text or isinstance(error, EOFError):
            text = f"the file is truncated: {text}"
        raise VoteSplatInputError(f"{what} {path} cannot be read ({text}); replace it with an intact file") from None
    return image


# Formats whose pixels are not the values written: a label image saved in one gets ids blurred into
# its neighbours' and ids that were never written (JPEG's 8x8 blocks ring at every mask edge).
LOSSY_LABEL_FORMATS = ("JPEG", "MPO")

# The modes nerfstudio's loader (``InputDataset.get_numpy_image``: ``np.array(image, dtype="uint8")``)
# reads as the right colours; others are read as wrong colours (CMYK as RGBA with alpha 0, palette
# indices as grey, 16-bit values wrapped) or fail on an assertion.
NERFSTUDIO_IMAGE_MODES = ("L", "RGB", "RGBA")


def image_file_size(path: PathLike, what: str = "image") -> Tuple[int, int]:
    """``(width, height)`` from an image file's header (nothing decoded); an unreadable file raises a named error."""
    return image_file_header(path, what)[0]


def image_file_header(path: PathLike, what: str = "image") -> Tuple[Tuple[int, int], str, str]:
    """``((width, height), PIL mode, file format)`` from an image file's header (nothing decoded).

    The format is the one the file's bytes hold (a JPEG named ``.png`` is "JPEG"); an unreadable
    file raises a named error.
    """
    path = Path(path)
    try:
        with Image.open(path) as image:
            return image.size, image.mode, str(image.format)
    except FileNotFoundError:
        raise VoteSplatInputError(f"{what} {path} does not exist") from None
    except Exception:  # not an image, or a header PIL cannot parse: load_image_file says which
        load_image_file(path, what)
        raise


def read_image_rgb(path: PathLike, what: str = "image") -> np.ndarray:
    """An image file's pixels as uint8 [H, W, 3] (alpha dropped, grey expanded); errors name the file.

    A 16-bit or float single-channel image is refused: PIL's conversion to RGB clips it at 255 rather
    than scaling it, which would hand SAM a mostly white picture. (16-bit RGB PNGs decode to 8 bits.)
    """
    image = load_image_file(path, what)
    if image.mode in ("I", "F") or image.mode.startswith("I;16"):
        raise VoteSplatInputError(
            f"{what} {path} is a {'float' if image.mode == 'F' else '16/32-bit'} single-channel image (PIL mode "
            f"{image.mode}), which would be clipped to 8 bits; save it as an 8-bit RGB or greyscale image"
        )
    return np.asarray(image.convert("RGB"))


def read_label_png(path: PathLike) -> np.ndarray:
    """Read a single-channel 8- or 16-bit label PNG as int32 [H, W]."""
    path = Path(path)
    image = load_image_file(path, "label image")
    check_label_format(path, str(image.format))
    mode = image.mode
    labels = np.array(image)
    if labels.ndim != 2 or mode not in ("L", "P", "I", "I;16", "I;16B", "I;16L"):
        raise VoteSplatInputError(
            f"label image {path} has mode {mode} with shape {labels.shape}; it must be a single-channel "
            "8- or 16-bit PNG holding mask ids (0 = no mask)"
        )
    labels = labels.astype(np.int32)
    if labels.size and labels.min() < 0:
        raise VoteSplatInputError(f"label image {path} holds negative ids; use 0 for no mask and 1..K for masks")
    return labels


def check_label_format(path: PathLike, file_format: str) -> None:
    """Refuse a label image stored in a lossy format (by its bytes, not its name): its ids would be wrong."""
    if file_format in LOSSY_LABEL_FORMATS:
        raise VoteSplatInputError(
            f"label image {path} is a {file_format} file, whose lossy compression changes mask ids at every "
            "edge and invents new ones; write label images as PNG (lossless)"
        )


def check_label_sizes_agree(shapes: Sequence[Tuple[int, ...]], paths: Sequence[PathLike]) -> None:
    """The label images of one view's levels (``paths``, read as ``shapes``) must share one size: each may be a
    scaled copy of the image, but the vote maps stack the levels pixel by pixel."""
    first_h, first_w = (int(v) for v in shapes[0][:2])
    for shape, path in zip(shapes[1:], paths[1:]):
        height, width = (int(v) for v in shape[:2])
        if (height, width) != (first_h, first_w):
            raise VoteSplatInputError(
                f"label image {path} is {width}x{height} but label image {paths[0]} of the same view is "
                f"{first_w}x{first_h}; save every level's label image of a view at one size (the image's)"
            )


def check_label_size(label_hw: Tuple[int, ...], image_hw: Tuple[int, ...], what: str) -> None:
    """Accept a label image of the image's size, or a uniformly scaled copy (to within a pixel).

    The scaled case covers nerfstudio reading downscaled images (``images_2/``) while the label
    images stay at full resolution.
    """
    label_h, label_w = (int(v) for v in label_hw)
    image_h, image_w = (int(v) for v in image_hw)
    if (label_h, label_w) == (image_h, image_w):
        return
    if min(label_h, label_w, image_h, image_w) > 0:
        # predicted image height/width if the label image were the image scaled uniformly
        height_from_width = label_h * image_w / label_w
        width_from_height = label_w * image_h / label_h
        if abs(height_from_width - image_h) <= 1.0 and abs(width_from_height - image_w) <= 1.0:
            return
    raise VoteSplatInputError(
        f"{what} is {label_w}x{label_h} but its image is {image_w}x{image_h}; "
        "label images must have the image's size (or be a uniformly scaled copy of it)"
    )
