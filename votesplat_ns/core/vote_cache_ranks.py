"""A vote cache made by several processes at once, one per GPU (or several CPU processes), all writing the one cache.

Rank r of N makes the views r, r + N, r + 2N, ... of the list (:func:`rank_share`). Each entry is written as
a single process writes it (:mod:`votesplat_ns.core.vote_cache`: temporary files renamed into place, the
``.votes.npz`` record last), so no rank ever reads another's half-written file, and the device is not part of
an entry's key (``MaskSource.config_key`` does not name it): the cache is the one a single process makes.

:func:`build_on_ranks` starts the ranks from this process (``spawn``) and waits for them; a launcher that
starts the processes itself (``torchrun``) gives each its share with :func:`rank_share` instead.

A rank that stops (an error, a kill, out of memory) stops the others. What they finished stays in the cache,
so the next build makes only the rest; their temporary files, and any labels file whose record they never
wrote, are removed, so no half-written entry is left. The error is one line
(:class:`~votesplat_ns.errors.VoteSplatInputError`) that names the rank and says what to do.

Over several hosts the same holds on a filesystem they share (renames are atomic on NFS and Lustre within a
folder): each host would run its own ranks on the views ``global rank, global rank + world size, ...``.
"""

from __future__ import annotations

import contextlib
import os
import queue as queue_module
import signal
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Sequence, Tuple, TypeVar

import torch

from votesplat_ns.core.mask_source_base import MaskSource
from votesplat_ns.core.ply_io import TEMP_MARKER
from votesplat_ns.core.vote_cache import VoteCache, VoteOptions, progress_bar
from votesplat_ns.errors import VoteSplatInputError, writing_into

T = TypeVar("T")
View = Tuple[int, Path]
# how often the parent looks at its ranks while none reports
_POLL_SECONDS = 0.2
# how long a rank that failed gets to deliver its message before the parent reads the queue one last time
_LAST_WORDS_SECONDS = 2.0


def rank_share(items: Sequence[T], rank: int, num_ranks: int) -> List[T]:
    """Rank ``rank``'s part of ``items``: those at positions rank, rank + num_ranks, ..."""
    if not 0 <= rank < num_ranks:
        raise ValueError(f"rank {rank} is outside 0..{num_ranks - 1}")
    return list(items)[rank::num_ranks]


@dataclass(frozen=True)
class _RankJob:
    """What one rank needs: sent to its process (pickled)."""

    cache_dir: Path
    source: MaskSource
    vote_options: VoteOptions
    views: Tuple[View, ...]
    keys: Tuple[str, ...]
    device: str
    torch_threads: int
    write_check: Optional[Tuple[Path, str]]  # (folder, flag) to name when the cache cannot be written


@contextlib.contextmanager
def _writing(write_check: Optional[Tuple[Path, str]]) -> Iterator[None]:
    if write_check is None:
        yield
        return
    with writing_into(*write_check):
        yield


def _run_rank(rank: int, job: _RankJob, messages) -> None:
    """One rank's process: make its views' entries, reporting each to the parent."""
    try:
        if job.device.startswith("cuda"):
            torch.cuda.set_device(torch.device(job.device))
        else:  # CPU ranks share the cores
            torch.set_num_threads(job.torch_threads)
        source = job.source.on_device(job.device)
        cache = VoteCache(job.cache_dir, source, job.vote_options)
        with _writing(job.write_check):
            cache.build_all(
                list(job.views), progress=False, keys=list(job.keys), on_built=lambda: messages.put(("built", rank))
            )
    except (ValueError, ImportError) as error:  # bad input: the parent prints it as one line
        messages.put(("failed", rank, _one_line(error), True))
        raise SystemExit(1) from None
    except KeyboardInterrupt:
        raise SystemExit(1) from None
    except BaseException as error:  # a bug or the machine (out of memory): keep the traceback for the log
        traceback.print_exc()
        messages.put(("failed", rank, f"{type(error).__name__}: {_one_line(error)}", False))
        raise SystemExit(1) from None


def _one_line(error: BaseException) -> str:
    return "; ".join(line.strip() for line in str(error).splitlines() if line.strip()) or type(error).__name__


def _exit_reason(exitcode: Optional[int]) -> str:
    if exitcode is None:
        return "still running"
    if exitcode < 0:
        try:
            return f"killed by signal {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exit status {exitcode}"


def build_on_ranks(
    cache: VoteCache,
    views: Sequence[View],
    devices: Sequence[str],
    progress: bool = True,
    description: Optional[str] = None,
    write_check: Optional[Tuple[Path, str]] = None,
) -> List[str]:
    """Make ``cache``'s missing entries for ``views`` in one process per device of ``devices`` (rank r on
    ``devices[r]``: ``"cuda:r"`` or ``"cpu"``) and return the views' keys in order, as ``cache.build_all`` does.

    ``write_check`` (folder, flag): a folder the cache cannot be written to is named as that flag in the error.
    Raises :class:`VoteSplatInputError` (one line) when a rank stops; the entries finished by then are kept.
    """
    num_ranks = len(devices)
    if num_ranks < 1:
        raise ValueError("build_on_ranks needs at least one device")
    views = [(int(index), Path(path)) for index, path in views]
    keys = [cache.view_key(path, index) for index, path in views]
    missing = sum(1 for key in keys if not cache.votes_path(key).is_file())
    if not missing:  # every entry is there: checked here, no process to start
        return cache.build_all(views, progress=progress, description=description, keys=keys)
    cpu_ranks = sum(1 for device in devices if not device.startswith("cuda"))
    threads = max(1, (os.cpu_count() or 1) // max(1, cpu_ranks))
    jobs = [
        _RankJob(
            cache.entry_dir.parent,
            cache.source,
            cache.vote_options,
            tuple(rank_share(views, rank, num_ranks)),
            tuple(rank_share(keys, rank, num_ranks)),
            str(devices[rank]),
            threads,
            write_check,
        )
        for rank in range(num_ranks)
    ]
    context = torch.multiprocessing.get_context("spawn")
    messages = context.Queue()
    processes = [context.Process(target=_run_rank, args=(rank, jobs[rank], messages)) for rank in range(num_ranks)]
    started = time.time()
    failures: Dict[int, Tuple[str, bool]] = {}  # rank: (its error in one line, whether it is bad input)
    display = progress_bar() if progress and missing else None
    try:
        with display if display is not None else contextlib.nullcontext():
            task = display.add_task(description or "Making vote maps", total=missing) if display is not None else None

            def read(message) -> None:
                if message[0] == "built" and display is not None and task is not None:
                    display.advance(task)
                elif message[0] == "failed":
                    failures[int(message[1])] = (str(message[2]), bool(message[3]))

            for process in processes:
                process.start()
            stopped = None
            while stopped is None:
                with contextlib.suppress(queue_module.Empty):
                    read(messages.get(timeout=_POLL_SECONDS))
                codes = [process.exitcode for process in processes]
                stopped = next((rank for rank, code in enumerate(codes) if code not in (None, 0)), None)
                if stopped is None and all(code == 0 for code in codes):
                    break
            if stopped is not None:
                deadline = time.time() + _LAST_WORDS_SECONDS
                while stopped not in failures and time.time() < deadline:
                    with contextlib.suppress(queue_module.Empty):
                        read(messages.get(timeout=_POLL_SECONDS))
            with contextlib.suppress(queue_module.Empty):
                while True:
                    read(messages.get_nowait())
    finally:
        for process in processes:
            if process.is_alive():
                process.terminate()
        for process in processes:
            process.join()
        messages.close()
        pids = [process.pid for process in processes if process.pid is not None]
        if any(process.exitcode != 0 for process in processes):
            _remove_leftovers(cache, pids, keys, started)
    if stopped is None:
        return keys
    done = sum(1 for key in keys if cache.votes_path(key).is_file())
    kept = f"the {done} of {len(keys)} vote maps made so far are kept in {cache.entry_dir}"
    reason, bad_input = failures.get(stopped, (_exit_reason(processes[stopped].exitcode), False))
    device = devices[stopped]
    if bad_input:
        raise VoteSplatInputError(f"{reason} (rank {stopped} of {num_ranks}, {device}; {kept})")
    raise VoteSplatInputError(
        f"rank {stopped} of {num_ranks} ({device}) stopped mid-way ({reason}); the other ranks were stopped and {kept}: "
        "run the command again to make the rest"
    )


def _remove_leftovers(cache: VoteCache, pids: Sequence[int], keys: Sequence[str], since: float) -> None:
    """After ranks were stopped: their temporary files, and labels files (of ``keys``, written since ``since``)
    whose record was never written."""
    folder = cache.entry_dir
    if not folder.is_dir():
        return
    markers = tuple(f"{TEMP_MARKER}{pid}-" for pid in pids)
    for path in folder.iterdir():
        if any(marker in path.name for marker in markers):
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
    for key in keys:
        labels = cache.labels_path(key)
        with contextlib.suppress(FileNotFoundError):
            if not cache.votes_path(key).is_file() and labels.stat().st_mtime >= since - 1.0:
                labels.unlink()
