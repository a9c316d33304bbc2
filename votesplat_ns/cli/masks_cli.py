"""Options of ``votesplat masks`` (alias ``votesplat-masks``): see ``ns/masks.py``, which makes the masks."""

from __future__ import annotations

from typing import Dict

from votesplat_ns.ns.masks import MasksConfig, make_masks

__all__ = ["MasksConfig", "main", "entrypoint"]


def main(config: MasksConfig) -> Dict[str, object]:
    """Make all views' vote maps and the previews; returns where they went."""
    return make_masks(config)


def entrypoint() -> None:
    """Console script ``votesplat-masks``, an alias of ``votesplat masks`` (lazy import: cli.main imports this module)."""
    from votesplat_ns.cli.main import alias

    alias("masks", "votesplat-masks")


if __name__ == "__main__":
    entrypoint()
