"""Every change this plugin makes to code it does not own, listed in one place.

They were written against nerfstudio 1.1.5 and gsplat 1.4.0 (:data:`WRITTEN_FOR`); :func:`apply`
warns once when an installed version differs, since any of them may then no longer fit.

Process-wide, applied by :func:`apply` when nerfstudio imports the method (every ``ns-*`` command):

* ``checkpoint safe globals`` (``ns/compat.py``): adds the numpy/pathlib types that nerfstudio 1.1.5
  pickles into checkpoints to torch's ``weights_only`` allow-list (torch >= 2.6 refuses them).
* ``one-line input errors`` (``cli/cli_errors.py``): wraps ``sys.excepthook`` so that a
  ``VoteSplatInputError`` ends any ``ns-*`` command with one line instead of a traceback.
* ``ns-export votesplat-instances`` (``ns/export.py``): a meta-path finder that adds our
  subcommand to ``nerfstudio.scripts.exporter``'s command union while it is imported (nerfstudio
  has no plugin point for exporters).

Scoped, applied where they are needed (listed here so that an upgrade checks them too):

* ``splatfacto rasterization`` (``ns/rasterizer.py``, when the model is built): rebinds
  ``nerfstudio.models.splatfacto.rasterization`` to our entry point (torch rasteriser on CPU,
  cameras recorded for the vote pass).
* ``resume trains`` (``ns/model.py``, ``load_state_dict`` / ``adopt_optimizers``): nerfstudio builds
  the optimisers before loading a checkpoint and splatfacto replaces the parameters (#3554).
* ``Tensor.cuda on CPU`` and ``LPIPS offline`` (``ns/compat.py``): context managers around
  nerfstudio code that calls ``.cuda()`` unconditionally or downloads AlexNet at init.
* gsplat's private ``cuda._torch_impl`` helpers (``core/rasterize_torch.py``, ``ns/retrofit.py``).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from importlib import metadata
from typing import Callable, Dict, Tuple

from votesplat_ns.cli.cli_errors import install_excepthook
from votesplat_ns.ns.compat import register_checkpoint_safe_globals

WRITTEN_FOR: Dict[str, str] = {"nerfstudio": "1.1.5", "gsplat": "1.4.0"}


@dataclass(frozen=True)
class Patch:
    name: str
    changes: str
    install: Callable[[], None]


def _install_export_hook() -> None:
    # imported here: ns/export.py imports nerfstudio's exporter machinery, which the hook patches
    from votesplat_ns.ns.export import install_ns_export_hook

    install_ns_export_hook()


PATCHES: Tuple[Patch, ...] = (
    Patch("checkpoint safe globals", "torch.serialization's weights_only allow-list", register_checkpoint_safe_globals),
    Patch("one-line input errors", "sys.excepthook", install_excepthook),
    Patch(
        "ns-export votesplat-instances",
        "nerfstudio.scripts.exporter's Commands (meta-path finder)",
        _install_export_hook,
    ),
)

_version_warned = False


def version_mismatches() -> Dict[str, Tuple[str, str]]:
    """{package: (installed, written for)} for every package whose installed version differs."""
    found = {}
    for package, expected in WRITTEN_FOR.items():
        try:
            installed = metadata.version(package)
        except metadata.PackageNotFoundError:
            installed = "not installed"
        if installed != expected:
            found[package] = (installed, expected)
    return found


def apply() -> None:
    """Apply the process-wide patches (idempotent); a failing patch warns and the others still apply."""
    global _version_warned
    mismatches = version_mismatches()
    if mismatches and not _version_warned:
        _version_warned = True
        listed = ", ".join(f"{name} {have} (written for {want})" for name, (have, want) in mismatches.items())
        warnings.warn(
            f"votesplat: {listed}; the plugin's patches (votesplat_ns/ns/patches.py) may not fit", RuntimeWarning
        )
    for patch in PATCHES:
        try:
            patch.install()
        except Exception as err:  # one broken patch must not break every ns-* command
            warnings.warn(f"votesplat: patch {patch.name!r} ({patch.changes}) not applied: {err}", RuntimeWarning)
