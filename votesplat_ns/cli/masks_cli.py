"""Options of ``votesplat masks`` : see ``ns/masks.py``, which makes the masks."""

from __future__ import annotations

from typing import Dict

from votesplat_ns.ns.masks import MasksConfig, make_masks

__all__ = ["MasksConfig", "main"]


def main(config: MasksConfig) -> Dict[str, object]:
    """Make all views' vote maps and the previews; returns where they went."""
    return make_masks(config)
