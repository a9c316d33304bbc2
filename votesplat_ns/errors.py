"""Bad user input as one line: the error type, how it is printed, and the checks every layer shares.

Below every layer (core, eval, ns and cli all import it; it imports none of them, nor nerfstudio).
Code that finds a bad input (a missing data folder, a device this machine lacks, ...) raises
:class:`VoteSplatInputError` with a message that says what to do. The ``sys.excepthook`` that
:func:`install_excepthook` adds (the method entry point installs it, so every ns-* command has
it) prints such an error as one line on stderr::

    ns-train votesplat: error: <message>

and Python exits with status 1, as for any uncaught exception. Every other exception keeps
its normal traceback: only errors we raise on purpose, with an actionable message, are
shortened. ``VoteSplatInputError`` is a ``ValueError``, so callers catching ``ValueError``
still catch it.

The plugin's own commands (``votesplat <subcommand>`` and ``ns-export votesplat-instances``) wrap
their work in :func:`one_line_errors`, which prints the same line and exits 1. The helpers below
turn the usual causes of a traceback into such an error in one place each: a folder that cannot be
written (:func:`check_writable_folder`, :func:`writing_into`) and a weights or checkpoint file torch
cannot read (:func:`load_failure_reason`, never relaying torch's advice to load with
``weights_only=False``). A run's config and checkpoint are checked in ``ns/run.py`` (``check_run``).
"""

from __future__ import annotations

import contextlib
import errno
import os
import pickle
import sys
import zipfile
from pathlib import Path
from types import TracebackType
from typing import Callable, Iterator, Optional, Sequence, Tuple, Type, Union

import torch

ExceptHook = Callable[[Type[BaseException], BaseException, Optional[TracebackType]], object]


class VoteSplatInputError(ValueError):
    """Bad user input; the message says what to do. ns-* commands print it as one line, without a traceback."""


# (command, subcommand) pairs named together in messages: ns-train votesplat, votesplat query, ...
_SUBCOMMANDS = {
    "ns-train": ("votesplat",),
    "ns-export": ("votesplat-instances",),
    "votesplat": ("masks", "export", "query", "click", "query-eval", "eval", "noisy-masks", "synth", "write-labels"),
}


def program_name(argv: Optional[Sequence[str]] = None) -> str:
    """The command as the user typed it: ``ns-train votesplat``, ``votesplat query``, ``ns-viewer``, ...

    Commands that are neither ns-* nor the plugin's own scripts (``pytest``, ``python``) give ``votesplat``.
    """
    argv = sys.argv if argv is None else argv
    prog = os.path.basename(argv[0]) if argv and argv[0] else ""
    if not prog.startswith(("ns-", "votesplat")):
        return "votesplat"
    if len(argv) > 1 and argv[1] in _SUBCOMMANDS.get(prog, ()):
        return f"{prog} {argv[1]}"
    return prog


def one_line_message(error: BaseException, argv: Optional[Sequence[str]] = None, prog: Optional[str] = None) -> str:
    """``<program>: error: <message>``, the message's lines joined into one (``prog`` default: from ``argv``)."""
    text = "; ".join(line.strip() for line in str(error).splitlines() if line.strip())
    return f"{prog or program_name(argv)}: error: {text or type(error).__name__}"


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


def device_problem(device: Union[str, torch.device]) -> Optional[str]:
    """Why this machine cannot compute on ``device``, as a clause for a one-line error ("CUDA is not available on
    this machine", a GPU index past the last, no MPS, a name torch does not parse); None when it can."""
    try:
        parsed = torch.device(device)
    except (RuntimeError, ValueError):
        return f"'{device}' is not a device (cpu, cuda, cuda:N or mps)"
    if parsed.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            return "CUDA is not available on this machine"
        if parsed.index is not None and parsed.index >= count:
            return f"this machine has {count} GPU{'s' if count != 1 else ''} (cuda:0 to cuda:{count - 1})"
    if parsed.type == "mps" and not torch.backends.mps.is_available():
        return "MPS (Apple GPU) is not available on this machine"
    return None


def check_device_available(device: Union[str, torch.device]) -> None:
    """Raise :class:`VoteSplatInputError` when ``device`` (ns-train's ``--machine.device-type``) is a device this
    machine does not have (:func:`device_problem`)."""
    problem = device_problem(device)
    if problem is None:
        return
    if str(device).split(":")[0] == "cuda":  # not torch.device(): the problem may be that the name does not parse
        raise VoteSplatInputError(
            f"{problem} (ns-train uses --machine.device-type cuda unless told otherwise); "
            "use --machine.device-type cpu (small scenes only) or run on a GPU"
        )
    raise VoteSplatInputError(
        f"{problem}; use --machine.device-type cpu (small scenes only), or --machine.device-type cuda on an NVIDIA GPU"
    )


@contextlib.contextmanager
def one_line_errors(
    catch: Tuple[Type[BaseException], ...] = (VoteSplatInputError,), prog: Optional[str] = None
) -> Iterator[None]:
    """Run a console script's work; an exception of a ``catch`` type ends it with one line on stderr and exit 1.

    ``prog`` names the command in the line (default: :func:`program_name` of ``sys.argv``).
    """
    try:
        yield
    except catch as error:
        sys.stderr.write(one_line_message(error, prog=prog) + "\n")
        sys.stderr.flush()
        raise SystemExit(1) from None


# errors that mean "this place cannot take our files", as opposed to a bug or a missing input
_WRITE_ERRNOS = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT, errno.ENOTDIR, errno.EEXIST}
_DISK_FULL_ERRNOS = {errno.ENOSPC, errno.EDQUOT}


def _nearest_existing(path: Path) -> Path:
    path = Path(os.path.abspath(path))
    while not os.path.lexists(path) and path != path.parent:
        path = path.parent
    return path


def check_writable_folder(folder: Union[str, Path], flag: str, given: Union[str, Path, None] = None) -> None:
    """Raise :class:`VoteSplatInputError` unless files can be made in ``folder`` (created if missing).

    Writes nothing: the nearest existing folder on the way must be a folder this process may
    write into (``os.access``, which also reports read-only file systems). The message names
    ``flag`` and the value the user gave for it (``given``, default ``folder``).
    """
    folder = Path(folder)
    given = folder if given is None else given
    existing = _nearest_existing(folder)
    if not existing.is_dir():
        raise VoteSplatInputError(f"{flag} {given}: {existing} is a file, not a folder; choose another {flag}")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise VoteSplatInputError(
            f"{flag} {given}: cannot write in {existing} (permission denied or read-only file system); "
            f"make it writable or choose another {flag}"
        )


def input_error_for_write(error: OSError, folder: Union[str, Path], flag: str) -> Optional[VoteSplatInputError]:
    """The :class:`VoteSplatInputError` for an ``OSError`` raised while writing into ``folder``, else None.

    Only errors about ``folder``, a path inside it or one of its parents, or inside a hidden sibling
    that is built to replace it (``.<folder name>...``), with an errno that means "cannot put files
    here" (permission, read-only, disk full, not a folder), qualify; anything else keeps its traceback.
    """
    if error.errno not in _WRITE_ERRNOS or not error.filename:
        return None
    target = Path(os.path.abspath(folder))
    failed = Path(os.path.abspath(os.fsdecode(error.filename)))
    related = failed == target or target in failed.parents or failed in target.parents
    if not related and target.parent in failed.parents:  # a staging sibling, e.g. .export.partial.tmp-123-abc
        related = failed.relative_to(target.parent).parts[0].startswith(f".{target.name}.")
    if not related:
        return None
    reason = error.strerror or os.strerror(error.errno)
    if error.errno in _DISK_FULL_ERRNOS:
        return VoteSplatInputError(
            f"{flag} {folder}: the disk is full ({reason} while writing {failed}); nothing was left half-written "
            f"and what was there is unchanged: free some space and run again, or choose another {flag} on another disk"
        )
    return VoteSplatInputError(
        f"{flag} {folder}: cannot write {failed} ({reason}); make it writable or choose another {flag}"
    )


@contextlib.contextmanager
def writing_into(folder: Union[str, Path], flag: str) -> Iterator[None]:
    """Turn an ``OSError`` about writing into ``folder`` into one :class:`VoteSplatInputError` naming ``flag``."""
    try:
        yield
    except OSError as error:
        converted = input_error_for_write(error, folder, flag)
        if converted is None:
            raise
        raise converted from error


def file_format_problem(path: Union[str, Path]) -> Optional[str]:
    """What is wrong with a file torch.load should read, judged from its bytes alone (None: looks fine)."""
    try:
        if not os.path.isfile(path) or zipfile.is_zipfile(path):  # torch.save writes a zip
            return None
        with open(path, "rb") as handle:
            head = handle.read(4)
    except OSError as error:  # no permission to read it, ...
        return f"it cannot be read ({error.strerror or type(error).__name__}; make it readable, e.g. chmod a+r)"
    if head.startswith(b"PK\x03\x04"):  # a zip that lost its end (central directory)
        return "the file is truncated or damaged"
    if not head.startswith(b"\x80"):  # nor a pickle (torch's legacy format)
        return "it is not a PyTorch weights file"
    return None


def load_failure_reason(error: BaseException, path: Union[str, Path, None] = None) -> str:
    """Why torch (or a model's ``load_state_dict``) could not use a file, in a few safe words.

    With ``path``, the file's own format decides first (torch's unpickler fails on arbitrary bytes
    with arbitrary exceptions). Never relays torch's text, which for a file that is not a weights
    file suggests loading it with ``weights_only=False``: unsafe for a file of unknown origin.
    """
    problem = file_format_problem(path) if path is not None else None
    if problem is not None:
        return problem
    text = str(error)
    if isinstance(error, (EOFError, zipfile.BadZipFile)) or any(
        marker in text for marker in ("PytorchStreamReader", "central directory", "unexpected EOF", "truncated")
    ):
        return "the file is truncated or damaged"
    if isinstance(error, pickle.UnpicklingError) or "invalid load key" in text or "Weights only load failed" in text:
        return "it is not a PyTorch weights file"
    if "state_dict" in text or "size mismatch" in text or isinstance(error, KeyError):
        return "it holds weights of another model"
    return f"torch could not read it ({type(error).__name__})"
