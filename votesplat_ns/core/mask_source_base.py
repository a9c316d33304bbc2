"""The interface every mask source implements (see :mod:`votesplat_ns.core.mask_sources`)."""

from __future__ import annotations

import abc
from typing import Any, Dict, List, Sequence, Tuple

import numpy as np

from votesplat_ns.core.image_files import PathLike
from votesplat_ns.errors import VoteSplatInputError


class MaskSource(abc.ABC):
    """Makes one label image per level for an image."""

    levels: Tuple[str, ...]
    # Whether masks_for_image may run for several views at once in threads (sources that read files);
    # a model-backed source (SAM on a GPU) keeps the default and is called one view at a time.
    thread_safe: bool = False
    # Whether masks_for_image may run for two views at once in threads although the source is not thread_safe:
    # it serialises itself what cannot run twice at once, so that the device works on one view while the host
    # works on the other (SAM on a GPU).
    overlaps_views: bool = False

    @abc.abstractmethod
    def masks_for_image(self, image: np.ndarray, image_path: PathLike, frame_index: int) -> List[np.ndarray]:
        """Label images (integer [h, w], one per level in ``self.levels``) for one view.

        Args:
            image: uint8 [H, W, 3], the pixels of ``image_path``.
            image_path: the image file the pixels came from.
            frame_index: the view's index in the caller's list of views (informational).
        """

    @abc.abstractmethod
    def config_key(self) -> Dict[str, Any]:
        """JSON-serialisable description of every argument that affects the output."""

    def view_fingerprint(self, image_path: PathLike, frame_index: int) -> str:
        """Digest of the per-view inputs other than the image pixels (default: none)."""
        return ""

    def on_device(self, device: str) -> "MaskSource":
        """This source for a process that runs on ``device`` (``"cuda:1"``, ``"cpu"``): one of the processes
        that make a cache together (:mod:`votesplat_ns.core.vote_cache_ranks`). A source that runs no model
        returns itself; the output must not depend on the device (``config_key`` does not name it)."""
        return self

    @property
    def name(self) -> str:
        return str(self.config_key()["type"])


def validate_levels(levels: Sequence[str], what: str) -> Tuple[str, ...]:
    levels = tuple(str(level) for level in levels)
    if not levels:
        raise VoteSplatInputError(f"{what}: give at least one mask level")
    if len(set(levels)) != len(levels):
        raise VoteSplatInputError(f"{what}: mask levels {levels} contain duplicates")
    return levels
