"""A vote cache made by several processes at once, one per GPU (or several CPU processes), all writing the one cache.

:func:`build_on_ranks` hands the views out as the ranks ask for them: the missing entries wait in one queue, and
each rank takes the next view when it has finished the one before (a source made in threads, which reads files
or, as SAM does, overlaps two views: the next few, made as one process makes them), so a rank that started
sooner, or runs faster, makes more of them.
The calling process is rank 0 itself, in a thread (it has torch, this package and the source loaded already),
and starts ranks 1 .. N-1 (``spawn``), which spend their first seconds importing and loading the model. Each entry is written as a single process writes it (:mod:`votesplat_ns.core.vote_cache`:
temporary files renamed into place, the ``.votes.npz`` record last), so no rank ever reads another's
half-written file, and the device is not part of an entry's key (``MaskSource.config_key`` does not name it):
the cache is the one a single process makes, whichever rank made which entry.

A launcher that starts the processes itself (``torchrun``) gives each a fixed share with :func:`rank_share`
instead: rank r of N makes the views r, r + N, r + 2N, ...

A rank that stops (an error, a kill, out of memory) stops the others; rank 0's thread finishes the view it is
making first, and so does it on Ctrl-C. What they finished stays in the cache, so the next build makes only
the rest; their temporary files, and any labels file whose record they never wrote, are removed, so no
half-written entry is left. The error is one line (:class:`~votesplat_ns.errors.VoteSplatInputError`) that
names the rank and says what to do.

Over several hosts the same holds on a filesystem they share (renames are atomic on NFS and Lustre within a
folder): each host would run its own ranks on the views ``global rank, global rank + world size, ...``.
"""

from __future__ import annotations

import contextlib
import os
import queue as queue_module
import signal
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, Iterator, List, Optional, Sequence, Tuple, TypeVar

import torch

from votesplat_ns.core.mask_source_base import MaskSource
from votesplat_ns.core.ply_io import TEMP_MARKER
from votesplat_ns.core.vote_cache import BUILD_THREADS, VoteCache, VoteOptions, build_threads, progress_bar
from votesplat_ns.errors import VoteSplatInputError, writing_into

T = TypeVar("T")
View = Tuple[int, Path]
# what the work queue holds: a view and its entry's key, then one None per rank (no more views)
WorkItem = Optional[Tuple[View, str]]
# how often the parent looks at its ranks while none reports, and rank 0's thread at its stop flag
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
    """What one rank needs: sent to its process (pickled); the views come from the work queue."""

    cache_dir: Path
    source: MaskSource
    vote_options: VoteOptions
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


def _rank_cache(job: _RankJob) -> VoteCache:
    """The cache as a rank on ``job.device`` writes it (its source moved there)."""
    if job.device.startswith("cuda"):
        torch.cuda.set_device(torch.device(job.device))  # per thread, so rank 0's thread may set it too
    else:  # CPU ranks share the cores
        torch.set_num_threads(job.torch_threads)
    return VoteCache(job.cache_dir, job.source.on_device(job.device), job.vote_options)


def _make_entries(
    cache: VoteCache,
    work,
    on_built: Callable[[], object],
    stop: Optional[threading.Event] = None,
    taken: Optional[Callable[[Sequence[str]], object]] = None,
) -> None:
    """Take views from ``work`` and make their entries until it says there are no more (``None``), or until
    ``stop`` is set (looked at between takes). A source that ``build_all`` makes in threads (``build_threads``:
    one that reads files, or SAM, two at a time) takes up to ``BUILD_THREADS`` views at a time, as one process
    does; another model's source takes one. ``taken(keys)``: told the keys of the views being made, () when
    they are done."""
    size = BUILD_THREADS if build_threads(cache.source) > 1 else 1
    while True:
        items, last = _next_items(work, stop, size)
        if items:
            if taken is not None:
                taken([key for _, key in items])
            cache.build_all(
                [view for view, _ in items], keys=[key for _, key in items], progress=False, on_built=on_built
            )
            if taken is not None:
                taken(())
        if last:
            break


def _next_items(work, stop: Optional[threading.Event], size: int) -> Tuple[List[Tuple[View, str]], bool]:
    """Up to ``size`` items of ``work`` (at least one unless none is left), and whether this rank is done: it took
    its ``None``, or ``stop`` is set."""
    first = _next_item(work, stop)
    if first is None:
        return [], True
    items = [first]
    while len(items) < size:
        try:
            item = work.get_nowait()
        except queue_module.Empty:
            break
        if item is None:  # this rank's end: the views it holds are its last
            return items, True
        items.append(item)
    return items, False


def _next_item(work, stop: Optional[threading.Event]) -> WorkItem:
    if stop is None:  # a rank's process: the parent terminates it if it must stop
        return work.get()
    while not stop.is_set():
        with contextlib.suppress(queue_module.Empty):
            return work.get(timeout=_POLL_SECONDS)
    return None


def _failure(error: BaseException) -> Tuple[str, bool]:
    """A rank's error as (one line, whether it is bad input); a bug's traceback is printed for the log."""
    if isinstance(error, (ValueError, ImportError)):  # bad input: the parent prints it as one line
        return _one_line(error), True
    traceback.print_exc()  # a bug or the machine (out of memory)
    return f"{type(error).__name__}: {_one_line(error)}", False


def _run_rank(rank: int, job: _RankJob, work, messages) -> None:
    """One rank's process: make the entries of the views it takes from ``work``, reporting each to the parent."""
    try:
        cache = _rank_cache(job)
        with _writing(job.write_check):
            _make_entries(cache, work, on_built=lambda: messages.put(("built", rank)))
    except KeyboardInterrupt:
        raise SystemExit(1) from None
    except BaseException as error:
        messages.put(("failed", rank, *_failure(error)))
        raise SystemExit(1) from None


class _OwnRank:
    """Rank 0, in a thread of the calling process: it has torch, this package and the source loaded already,
    so it makes entries while the other ranks start. ``stop`` stops it between two views; its error, if any,
    is ``failure`` once the thread has ended."""

    def __init__(self, job: _RankJob, work, on_built: Callable[[], object]):
        self.stop = threading.Event()
        self.failure: Optional[Tuple[str, bool]] = None  # (its error in one line, whether it is bad input)
        self.making: Tuple[str, ...] = ()  # the keys of the entries it is making
        self._thread = threading.Thread(
            target=self._run, args=(job, work, on_built), name="votesplat-rank-0", daemon=True
        )

    def _run(self, job: _RankJob, work, on_built: Callable[[], object]) -> None:
        threads = torch.get_num_threads()
        try:
            cache = _rank_cache(job)
            with _writing(job.write_check):
                _make_entries(cache, work, on_built, stop=self.stop, taken=self._taken)
        except BaseException as error:  # noqa: BLE001 - handed to the main thread, which raises it as one line
            self.failure = _failure(error)
        finally:
            torch.set_num_threads(threads)

    def _taken(self, keys: Sequence[str]) -> None:
        self.making = tuple(keys)

    def start(self) -> None:
        self._thread.start()

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def join(self) -> None:
        """Wait for the thread (it finishes the view it is making; set ``stop`` first to end it there)."""
        if self._thread.ident is not None:
            self._thread.join()


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
    """Make ``cache``'s missing entries for ``views`` on one rank per device of ``devices`` (rank r on
    ``devices[r]``: ``"cuda:r"`` or ``"cpu"``; rank 0 is a thread of this process, the others processes it
    starts) and return the views' keys in order, as ``cache.build_all`` does. Each rank takes the next missing
    view when it is free.

    ``write_check`` (folder, flag): a folder the cache cannot be written to is named as that flag in the error.
    Raises :class:`VoteSplatInputError` (one line) when a rank stops; the entries finished by then are kept.
    """
    num_ranks = len(devices)
    if num_ranks < 1:
        raise ValueError("build_on_ranks needs at least one device")
    views = [(int(index), Path(path)) for index, path in views]
    keys = [cache.view_key(path, index) for index, path in views]
    todo = [(view, key) for view, key in zip(views, keys) if not cache.votes_path(key).is_file()]
    if not todo:  # every entry is there: checked here, no process to start
        return cache.build_all(views, progress=progress, description=description, keys=keys)
    cpu_ranks = sum(1 for device in devices if not device.startswith("cuda"))
    threads = max(1, (os.cpu_count() or 1) // max(1, cpu_ranks))
    jobs = [
        _RankJob(cache.entry_dir.parent, cache.source, cache.vote_options, str(device), threads, write_check)
        for device in devices
    ]
    context = torch.multiprocessing.get_context("spawn")
    messages = context.Queue()
    work = context.Queue()
    for item in todo:
        work.put(item)
    for _ in range(num_ranks):
        work.put(None)
    processes = [
        context.Process(target=_run_rank, args=(rank, jobs[rank], work, messages)) for rank in range(1, num_ranks)
    ]
    started = time.time()
    failures: Dict[int, Tuple[str, bool]] = {}  # rank: (its error in one line, whether it is bad input)
    stopped: Optional[int] = None  # the rank that stopped
    finished = False
    display = progress_bar() if progress else None
    task = None

    def advance() -> None:  # from the main thread and rank 0's (rich's Progress takes a lock)
        if display is not None and task is not None:
            display.advance(task)

    own = _OwnRank(jobs[0], work, on_built=advance)
    try:
        with display if display is not None else contextlib.nullcontext():
            task = display.add_task(description or "Making vote maps", total=len(todo)) if display is not None else None

            def read(message) -> None:
                if message[0] == "built":
                    advance()
                elif message[0] == "failed":
                    failures[int(message[1])] = (str(message[2]), bool(message[3]))

            for process in processes:  # first: they take seconds to start
                process.start()
            own.start()
            while True:
                with contextlib.suppress(queue_module.Empty):
                    read(messages.get(timeout=_POLL_SECONDS))
                own_done = not own.running
                if own_done and own.failure is not None:
                    stopped = 0
                    break
                codes = [process.exitcode for process in processes]
                stopped = next((rank for rank, code in enumerate(codes, start=1) if code not in (None, 0)), None)
                if stopped is not None or (own_done and all(code == 0 for code in codes)):
                    break
            own.stop.set()  # rank 0 stops after the view it is making (it has none left when all went well)
            if stopped is not None and stopped > 0:
                deadline = time.time() + _LAST_WORDS_SECONDS
                while stopped not in failures and time.time() < deadline:
                    with contextlib.suppress(queue_module.Empty):
                        read(messages.get(timeout=_POLL_SECONDS))
            with contextlib.suppress(queue_module.Empty):
                while True:
                    read(messages.get_nowait())
            finished = stopped is None
    finally:
        try:
            own.stop.set()
            for process in processes:
                if process.is_alive():
                    process.terminate()
            for process in processes:
                process.join()
            own.join()  # it finishes the view it is making (a second Ctrl-C ends the wait)
        finally:
            messages.close()
            work.cancel_join_thread()  # the views no rank took are dropped, not waited on at exit
            work.close()
            if not finished:
                pids = [process.pid for process in processes if process.pid is not None]
                busy = own.making if own.running else ()  # rank 0 still writes them: leave them alone
                if not busy:
                    pids.append(os.getpid())
                _remove_leftovers(cache, pids, [key for key in keys if key not in busy], started)
    if stopped is None:
        return keys
    done = sum(1 for key in keys if cache.votes_path(key).is_file())
    kept = f"the {done} of {len(keys)} vote maps made so far are kept in {cache.entry_dir}"
    if stopped == 0:
        reason, bad_input = own.failure or ("stopped", False)
    else:
        reason, bad_input = failures.get(stopped, (_exit_reason(processes[stopped - 1].exitcode), False))
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
