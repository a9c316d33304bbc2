"""One-line errors for bad input to ``ns-train votesplat`` (and the other ns-* commands).

Code that finds a bad input (a missing data folder, a device this machine lacks, ...) raises
:class:`VoteSplatInputError` with a message that says what to do. The ``sys.excepthook`` that
:func:`install_excepthook` adds (the method entry point installs it, so every ns-* command has
it) prints such an error as one line on stderr::

    ns-train votesplat: error: <message>

and Python exits with status 1, as for any uncaught exception. Every other exception keeps
its normal traceback: only errors we raise on purpose, with an actionable message, are
shortened. ``VoteSplatInputError`` is a ``ValueError``, so callers catching ``ValueError``
still catch it.
"""

from __future__ import annotations

import os
import sys
from types import TracebackType
from typing import Callable, Optional, Sequence, Type, Union

import torch

ExceptHook = Callable[[Type[BaseException], BaseException, Optional[TracebackType]], object]


class VoteSplatInputError(ValueError):
    """Bad user input; the message says what to do. ns-* commands print it as one line, without a traceback."""


def program_name(argv: Optional[Sequence[str]] = None) -> str:
    """``ns-train votesplat`` for ``ns-train votesplat ...``, the command's name for other ns-* commands."""
    argv = sys.argv if argv is None else argv
    prog = os.path.basename(argv[0]) if argv and argv[0] else ""
    if not prog.startswith("ns-"):
        return "votesplat"
    if len(argv) > 1 and argv[1] == "votesplat":
        return f"{prog} votesplat"
    return prog


def one_line_message(error: BaseException, argv: Optional[Sequence[str]] = None) -> str:
    """``<program>: error: <message>``, the message's lines joined into one."""
    text = "; ".join(line.strip() for line in str(error).splitlines() if line.strip())
    return f"{program_name(argv)}: error: {text or type(error).__name__}"


def install_excepthook() -> None:
    """Print uncaught :class:`VoteSplatInputError` as one line on stderr; leave all other exceptions alone.

    Idempotent: installing twice keeps one wrapper around the hook that was there first.
    """
    previous: ExceptHook = sys.excepthook
    if getattr(previous, "_votesplat_input_errors", False):
        return

    def excepthook(exc_type: Type[BaseException], exc: BaseException, tb: Optional[TracebackType]) -> object:
        if isinstance(exc, VoteSplatInputError):
            sys.stderr.write(one_line_message(exc) + "\n")
            sys.stderr.flush()
            return None
        return previous(exc_type, exc, tb)

    excepthook._votesplat_input_errors = True  # type: ignore[attr-defined]
    excepthook.previous = previous  # type: ignore[attr-defined]
    sys.excepthook = excepthook


def check_device_available(device: Union[str, torch.device]) -> None:
    """Raise :class:`VoteSplatInputError` when ``device`` is a CUDA or MPS device this machine does not have."""
    kind = torch.device(device).type
    if kind == "cuda" and not torch.cuda.is_available():
        raise VoteSplatInputError(
            "CUDA is not available on this machine (ns-train uses --machine.device-type cuda unless told otherwise); "
            "use --machine.device-type cpu (small scenes only) or run on a GPU"
        )
    if kind == "mps" and not torch.backends.mps.is_available():
        raise VoteSplatInputError(
            "MPS (Apple GPU) is not available on this machine; use --machine.device-type cpu (small scenes only), "
            "or --machine.device-type cuda on an NVIDIA GPU"
        )
