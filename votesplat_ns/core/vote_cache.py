"""On-disk cache of per-view vote maps, so masks are made once and reused across runs.

Layout (``cache_dir`` is chosen by the caller, next to the outputs, never inside the dataset)::

    <cache_dir>/<source>-<config digest>/config.json        the arguments the entries were made with
    <cache_dir>/<source>-<config digest>/<view key>.labels.npy  uint16/int32 [L, H, W], memory-mappable
    <cache_dir>/<source>-<config digest>/<view key>.votes.npz   centroid tables + what the labels file must be

- The config digest covers the source's ``config_key()``, the vote options and the cache format
  version; a different configuration lives in a different folder, so changing an argument
  rebuilds while switching back reuses the old entries.
- A view key is the sha256 of the image file's bytes plus the source's per-view fingerprint
  (e.g. the label files it reads), so an edited image or mask is rebuilt.
- Each file is written to a temp file in the same folder and moved into place with os.replace;
  the .votes.npz is written last and is the entry's commit record. A missing, truncated or
  unreadable entry is rebuilt, so an interrupted build resumes where it stopped and never
  yields a partial entry.
- An entry is validated when first read in a process: shapes and dtype against its record, and
  every label id within its level's centroid table (a damaged labels file could otherwise index
  past the table on the first vote step). A damaged entry is rebuilt; the first one per cache
  is reported with a warning, the others are counted in ``rebuilt_damaged``.
"""

from __future__ import annotations

import hashlib
import json
import time
import warnings
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import BinaryIO, Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

from votesplat_ns.core.image_files import file_digest, read_image_rgb
from votesplat_ns.core.mask_source_base import MaskSource
from votesplat_ns.core.ply_io import TEMP_MARKER, atomic_write
from votesplat_ns.core.vote_maps import DEFAULT_BORDER_MASKS, VoteMaps, vote_maps_from_labels

PathLike = Union[str, Path]
ImageLoader = Callable[[int, Path], np.ndarray]

CACHE_FORMAT_VERSION = 1
_TEMP_MARKER = TEMP_MARKER  # atomic_write names its temporary files with it
_STALE_TEMP_SECONDS = 3600.0
# Views built at once by a source that reads files (build_all)
BUILD_THREADS = 4


@dataclass(frozen=True)
class VoteOptions:
    """Options of the 2D vote construction that change the cached result."""

    border_masks: str = DEFAULT_BORDER_MASKS
    """What a mask touching the image border becomes: "vote", "mask_only" or "drop" (vote_maps.mask_centroids)."""


def load_image_rgb(path: PathLike) -> np.ndarray:
    """An image file's pixels as uint8 [H, W, 3] (alpha dropped, grey expanded); a broken file is named."""
    return read_image_rgb(path)


def atomic_write_bytes(path: Path, writer: Callable[[BinaryIO], object]) -> None:
    """Write a file atomically (``ply_io.atomic_write``, honours the umask): ``writer(file)`` fills it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as handle:
        writer(handle)


class VoteCache:
    """Vote maps per view, made by ``source`` once and memory-mapped from ``cache_dir`` afterwards."""

    def __init__(
        self,
        cache_dir: PathLike,
        source: MaskSource,
        vote_options: VoteOptions = VoteOptions(),
        max_open_entries: int = 8,
    ):
        self.source = source
        self.vote_options = vote_options
        self.config = {
            "format_version": CACHE_FORMAT_VERSION,
            "source": source.config_key(),
            "levels": list(source.levels),
            "vote_options": asdict(vote_options),
        }
        config_text = json.dumps(self.config, sort_keys=True, indent=2)
        digest = hashlib.sha256(config_text.encode()).hexdigest()[:16]
        self.entry_dir = Path(cache_dir) / f"{source.name}-{digest}"
        self._config_text = config_text
        self._config_written = self._check_config_file(config_text)
        # open memmaps hold a file descriptor each, so only a few stay open
        self._open: "OrderedDict[str, VoteMaps]" = OrderedDict()
        self._max_open = max(1, int(max_open_entries))
        self._key_memo: Dict[Tuple[str, int], Tuple[Tuple[int, int], str]] = {}
        # labels files whose ids were checked in this process, by (key, size, mtime): a full scan per file
        self._validated: Dict[str, Tuple[int, int]] = {}
        self.rebuilt_damaged = 0

    # ------------------------------------------------------------------ configuration
    def _check_config_file(self, config_text: str) -> bool:
        """Whether config.json is there and matches; entries made with other arguments are removed.

        config.json is written with the first entry (``_write_entry``), so a cache that is only read,
        or a build that fails before its first entry, writes nothing.
        """
        config_path = self.entry_dir / "config.json"
        if config_path.is_file():
            try:
                stored = json.loads(config_path.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                stored = None
            if stored == json.loads(config_text):
                return True
            # same folder name but other arguments: the entries cannot be trusted; files the cache does not
            # write (a user's, dropped into the folder) are kept
            kept = []
            for path in sorted(self.entry_dir.iterdir()):
                if path.is_file() and not path.is_symlink() and is_cache_file(path.name):
                    path.unlink()
                elif not path.name.startswith("."):
                    kept.append(path.name)
            also = f" (kept {', '.join(kept[:3])}{' ...' if len(kept) > 3 else ''}, which the cache does not write)"
            warnings.warn(
                f"vote cache {self.entry_dir} was made with other arguments; rebuilding it{also if kept else ''}"
            )
        return False

    # ------------------------------------------------------------------ keys and paths
    def view_key(self, image_path: PathLike, frame_index: int) -> str:
        """Content key of a view: its image bytes and the source's per-view inputs."""
        image_path = Path(image_path)
        stat = image_path.stat()
        memo_key = (str(image_path.resolve()), int(frame_index))
        signature = (stat.st_size, stat.st_mtime_ns)
        memo = self._key_memo.get(memo_key)
        if memo is not None and memo[0] == signature:
            return memo[1]
        digest = hashlib.sha256()
        digest.update(file_digest(image_path).encode())
        digest.update(b"|")
        digest.update(self.source.view_fingerprint(image_path, frame_index).encode())
        key = digest.hexdigest()[:32]
        self._key_memo[memo_key] = (signature, key)
        return key

    def labels_path(self, key: str) -> Path:
        return self.entry_dir / f"{key}.labels.npy"

    def votes_path(self, key: str) -> Path:
        return self.entry_dir / f"{key}.votes.npz"

    # ------------------------------------------------------------------ reading
    def load(self, key: str) -> Optional[VoteMaps]:
        """The entry for ``key`` (labels memory-mapped), or None if absent or unusable."""
        if key in self._open:
            self._open.move_to_end(key)
            return self._open[key]
        votes_path, labels_path = self.votes_path(key), self.labels_path(key)
        if not votes_path.is_file():
            return None
        try:
            vote_maps = self._read_entry(key, votes_path, labels_path)
        except Exception as error:  # any unreadable or inconsistent entry is rebuilt
            if self.rebuilt_damaged == 0:
                warnings.warn(
                    f"vote cache entry {votes_path.name} in {self.entry_dir} is damaged ({type(error).__name__}: {error}); "
                    "rebuilding it (and any other damaged entry of this cache)"
                )
            self.rebuilt_damaged += 1
            self._remove_entry(key)
            return None
        self._open[key] = vote_maps
        while len(self._open) > self._max_open:
            self._open.popitem(last=False)
        return vote_maps

    def _read_entry(self, key: str, votes_path: Path, labels_path: Path) -> VoteMaps:
        with np.load(votes_path, allow_pickle=False) as record:
            stored_key = str(record["key"])
            num_levels = int(record["num_levels"])
            labels_shape = tuple(int(v) for v in record["labels_shape"])
            labels_dtype = np.dtype(str(record["labels_dtype"]))
            level_names = tuple(str(v) for v in record["level_names"])
            centroids = [np.array(record[f"centroids_{level}"], dtype=np.float32) for level in range(num_levels)]
        if stored_key != key:
            raise ValueError(f"entry holds key {stored_key}")
        labels = np.load(labels_path, mmap_mode="r", allow_pickle=False)
        if labels.shape != labels_shape or labels.dtype != labels_dtype:
            raise ValueError(f"labels are {labels.dtype}{labels.shape}, the record says {labels_dtype}{labels_shape}")
        vote_maps = VoteMaps(labels=labels, centroids=centroids, level_names=level_names)
        if level_names != tuple(self.source.levels):
            raise ValueError(f"entry has levels {level_names}, expected {tuple(self.source.levels)}")
        stat = labels_path.stat()
        signature = (stat.st_size, stat.st_mtime_ns)
        if self._validated.get(key) != signature:
            _check_label_ids(labels, centroids)
            self._validated[key] = signature
        return vote_maps

    def _remove_entry(self, key: str) -> None:
        self._open.pop(key, None)
        for path in (self.votes_path(key), self.labels_path(key)):
            try:
                path.unlink()
            except FileNotFoundError:
                pass

    # ------------------------------------------------------------------ building
    def _build(self, key: str, frame_index: int, image_path: Path, image_loader: Optional[ImageLoader]) -> VoteMaps:
        image = image_loader(frame_index, image_path) if image_loader is not None else load_image_rgb(image_path)
        label_images = self.source.masks_for_image(image, image_path, frame_index)
        if len(label_images) != len(self.source.levels):
            raise ValueError(
                f"mask source '{self.source.name}' returned {len(label_images)} label images for {image_path}, "
                f"expected one per level {list(self.source.levels)}"
            )
        vote_maps = vote_maps_from_labels(
            label_images, border_masks=self.vote_options.border_masks, level_names=self.source.levels
        )
        self._write_entry(key, vote_maps)
        return vote_maps

    def _write_entry(self, key: str, vote_maps: VoteMaps) -> None:
        if not self._config_written:
            config_text = self._config_text
            atomic_write_bytes(self.entry_dir / "config.json", lambda handle: handle.write(config_text.encode()))
            self._config_written = True
        labels = np.ascontiguousarray(vote_maps.labels)
        atomic_write_bytes(self.labels_path(key), lambda handle: np.save(handle, labels, allow_pickle=False))
        record = {
            "key": np.array(key),
            "num_levels": np.array(vote_maps.num_levels),
            "labels_shape": np.array(labels.shape, dtype=np.int64),
            "labels_dtype": np.array(labels.dtype.str),
            "level_names": np.array(list(vote_maps.level_names), dtype=str),
        }
        for level, table in enumerate(vote_maps.centroids):
            record[f"centroids_{level}"] = table
        # written last: an entry without its .votes.npz is not an entry
        atomic_write_bytes(self.votes_path(key), lambda handle: np.savez(handle, **record))

    def get(self, frame_index: int, image_path: PathLike, image_loader: Optional[ImageLoader] = None) -> VoteMaps:
        """Vote maps of one view: from the cache if a valid entry exists, else made and stored.

        Args:
            frame_index: the view's index (passed to the mask source).
            image_path: the image file; its bytes key the entry.
            image_loader: ``(frame_index, image_path) -> uint8 [H, W, 3]`` returning that file's
                pixels; defaults to reading the file.
        """
        image_path = Path(image_path)
        key = self.view_key(image_path, frame_index)
        cached = self.load(key)
        if cached is not None:
            return cached
        self._build(key, frame_index, image_path, image_loader)
        loaded = self.load(key)
        if loaded is None:
            raise RuntimeError(f"vote cache entry {self.votes_path(key)} could not be read back after writing it")
        return loaded

    def build_all(
        self,
        views: Sequence[Tuple[int, PathLike]],
        image_loader: Optional[ImageLoader] = None,
        progress: bool = True,
        description: Optional[str] = None,
        keys: Optional[Sequence[str]] = None,
        on_built: Optional[Callable[[], object]] = None,
    ) -> List[str]:
        """Make every missing entry (with a progress bar) and return the views' keys in order.

        Entries already present and readable are reused, so an interrupted build resumes. Sources that
        read files (``MaskSource.thread_safe``) build BUILD_THREADS views at a time: decoding images and
        label files and writing entries release the GIL. A source that overlaps views (``overlaps_views``:
        SAM) builds two at a time, one on the device and one on the host. ``keys``: the views' keys when the
        caller has them (``view_key`` reads every image file); ``on_built``: called after each entry made, in
        order.
        """
        self._remove_stale_temp_files()
        if keys is None:
            keys = [self.view_key(Path(path), index) for index, path in views]
        elif len(keys) != len(views):
            raise ValueError(f"{len(keys)} keys given for {len(views)} views")
        keys = list(keys)
        missing = [i for i, key in enumerate(keys) if not self._entry_usable(key)]
        if missing:
            text = description or f"Making vote maps ({self.source.name} masks)"
            steps = _progress(missing, text, enabled=progress)
            threads = build_threads(self.source) if len(missing) > 1 else 1

            def build(i: int) -> None:
                index, path = views[i]
                self._build(keys[i], index, Path(path), image_loader)

            pool = ThreadPoolExecutor(max_workers=threads) if threads > 1 else None
            try:
                # in order, so the progress bar advances and the first error is raised as it happens
                done = pool.map(build, missing) if pool is not None else map(build, missing)
                for _ in zip(steps, done):
                    if on_built is not None:
                        on_built()
            finally:
                if pool is not None:
                    pool.shutdown(cancel_futures=True)
                # stop the progress display now: closed at interpreter exit instead, it fails with its own traceback
                close = getattr(steps, "close", None)
                if close is not None:
                    close()
        return keys

    def _entry_usable(self, key: str) -> bool:
        return self.load(key) is not None

    def _remove_stale_temp_files(self) -> None:
        if not self.entry_dir.is_dir():
            return
        now = time.time()
        for path in self.entry_dir.iterdir():
            if _TEMP_MARKER in path.name and path.is_file():
                try:
                    if now - path.stat().st_mtime > _STALE_TEMP_SECONDS:
                        path.unlink()
                except FileNotFoundError:
                    pass


def build_threads(source: MaskSource) -> int:
    """Views a source's entries are made for at once (``build_all``): BUILD_THREADS for a source that reads files,
    two for one that overlaps views, else one."""
    if source.thread_safe:
        return BUILD_THREADS
    return 2 if source.overlaps_views else 1


def is_cache_file(name: str) -> bool:
    """Whether a file name in an entry folder is one the cache writes (config.json, entries, their temporary files)."""
    return name == "config.json" or name.endswith((".labels.npy", ".votes.npz")) or _TEMP_MARKER in name


def _check_label_ids(labels: np.ndarray, centroids: Sequence[np.ndarray]) -> None:
    """Raise ValueError unless every level's ids lie in 0..K, K + 1 being its centroid table's length."""
    for level, table in enumerate(centroids):
        level_labels = np.asarray(labels[level])
        if not level_labels.size:
            continue
        low, high = int(level_labels.min()), int(level_labels.max())
        if low < 0 or high >= table.shape[0]:
            raise ValueError(
                f"level {level} holds label ids {low}..{high}, outside its masks' ids 0..{table.shape[0] - 1}"
            )


def progress_bar():
    """A rich progress display (``with progress_bar() as bar: bar.add_task(...)``) that shows images per second,
    elapsed and remaining time."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        ProgressColumn,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )
    from rich.text import Text

    class ImagesPerSecond(ProgressColumn):
        def render(self, task) -> Text:
            return Text("" if task.speed is None else f"{task.speed:.2f} images/s")

    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        ImagesPerSecond(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        transient=False,
    )


def _progress(items: Sequence[int], description: str, enabled: bool):
    """The items, shown as a progress bar with images per second, elapsed and remaining time (``close()`` ends it)."""
    if not enabled:
        return items
    progress = progress_bar()

    def steps():
        with progress:
            yield from progress.track(items, total=len(items), description=description)

    return steps()
