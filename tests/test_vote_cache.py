"""Vote cache: hits, misses on changed inputs, atomic writes, resuming, damaged entries."""

import os
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import votesplat_ns.core.vote_cache as vote_cache_module
from votesplat_ns.core.mask_sources import FolderMaskSource, MaskSource
from votesplat_ns.core.vote_cache import VoteCache, VoteOptions


class ThresholdMaskSource(MaskSource):
    """A real (if simple) source: one mask per colour channel above a threshold; counts its calls."""

    def __init__(self, threshold: int = 128, fail_on: str = ""):
        self.levels = ("red", "green")
        self.threshold = threshold
        self.fail_on = fail_on
        self.calls = []

    def masks_for_image(self, image, image_path, frame_index):
        if self.fail_on and Path(image_path).name == self.fail_on:
            raise KeyboardInterrupt  # stands in for the user stopping a long build
        self.calls.append(Path(image_path).name)
        return [(image[..., c] > self.threshold).astype(np.int32) for c in (0, 1)]

    def config_key(self):
        return {"type": "threshold", "threshold": self.threshold}


def write_views(folder: Path, count: int = 3) -> list:
    folder.mkdir(parents=True, exist_ok=True)
    views = []
    for i in range(count):
        image = np.zeros((24, 32, 3), dtype=np.uint8)
        image[4 + i : 12 + i, 5:15, 0] = 200  # red block
        image[14:20, 16 + i : 28, 1] = 220  # green block
        path = folder / f"frame_{i:03d}.png"
        Image.fromarray(image).save(path)
        views.append((i, path))
    return views


def entry_files(cache: VoteCache) -> list:
    return sorted(p.name for p in cache.entry_dir.iterdir() if p.name != "config.json")


def test_cache_hit_reuses_entries_and_memory_maps_labels(tmp_path):
    views = write_views(tmp_path / "images")
    source = ThresholdMaskSource()
    cache = VoteCache(tmp_path / "cache", source)
    keys = cache.build_all(views, progress=False)
    assert source.calls == ["frame_000.png", "frame_001.png", "frame_002.png"]
    assert len(set(keys)) == 3 and (cache.entry_dir / "config.json").is_file()

    vote_maps = cache.get(0, views[0][1])
    assert isinstance(vote_maps.labels, np.memmap) and vote_maps.labels.dtype == np.uint16
    assert vote_maps.labels.shape == (2, 24, 32) and vote_maps.level_names == ("red", "green")
    red_rows, red_cols = np.nonzero(vote_maps.labels[0] == 1)
    np.testing.assert_array_equal(
        vote_maps.centroids[0][1], [np.floor(red_cols.mean() + 0.5), np.floor(red_rows.mean() + 0.5)]
    )

    # a new process (new VoteCache object) reuses everything
    fresh_source = ThresholdMaskSource()
    assert VoteCache(tmp_path / "cache", fresh_source).build_all(views, progress=False) == keys
    assert fresh_source.calls == []


def test_changed_arguments_or_inputs_miss(tmp_path):
    views = write_views(tmp_path / "images", count=2)
    VoteCache(tmp_path / "cache", ThresholdMaskSource()).build_all(views, progress=False)

    other_threshold = ThresholdMaskSource(threshold=100)
    VoteCache(tmp_path / "cache", other_threshold).build_all(views, progress=False)
    assert len(other_threshold.calls) == 2

    keep_border = ThresholdMaskSource()
    VoteCache(tmp_path / "cache", keep_border, VoteOptions(border_masks="drop")).build_all(views, progress=False)
    assert len(keep_border.calls) == 2

    # the original arguments again: still cached
    same = ThresholdMaskSource()
    VoteCache(tmp_path / "cache", same).build_all(views, progress=False)
    assert same.calls == []

    # an edited image is a new entry
    image = np.array(Image.open(views[1][1]))
    image[0, 0, 2] = 1
    Image.fromarray(image).save(views[1][1])
    edited = ThresholdMaskSource()
    VoteCache(tmp_path / "cache", edited).build_all(views, progress=False)
    assert edited.calls == ["frame_001.png"]


def test_edited_label_file_of_a_folder_source_misses(tmp_path):
    views = write_views(tmp_path / "images", count=1)
    labels = np.zeros((24, 32), dtype=np.uint16)
    labels[5:10, 5:10] = 1
    (tmp_path / "masks" / "object").mkdir(parents=True)
    Image.fromarray(labels).save(tmp_path / "masks" / "object" / "frame_000.png")
    cache = VoteCache(tmp_path / "cache", FolderMaskSource(tmp_path / "masks"))
    first = cache.get(0, views[0][1])
    np.testing.assert_array_equal(first.centroids[0][1], [7, 7])
    labels[5:10, 5:10] = 0
    labels[12:15, 20:25] = 1
    Image.fromarray(labels).save(tmp_path / "masks" / "object" / "frame_000.png")
    second = VoteCache(tmp_path / "cache", FolderMaskSource(tmp_path / "masks")).get(0, views[0][1])
    np.testing.assert_array_equal(second.centroids[0][1], [22, 13])


def test_interrupted_build_resumes_and_leftovers_are_never_read(tmp_path):
    views = write_views(tmp_path / "images", count=3)
    stopping = ThresholdMaskSource(fail_on="frame_002.png")
    with pytest.raises(KeyboardInterrupt):
        VoteCache(tmp_path / "cache", stopping).build_all(views, progress=False)
    assert stopping.calls == ["frame_000.png", "frame_001.png"]

    cache = VoteCache(tmp_path / "cache", ThresholdMaskSource())
    key = cache.view_key(views[2][1], 2)
    # what a crash mid-write could leave: a half-written temp file and a labels file without its record
    cache.votes_path(key).with_name(f".{key}.votes.npz.tmp-crash").write_bytes(b"PK\x03\x04 half")
    np.save(cache.labels_path(key), np.zeros((2, 3, 3), dtype=np.uint16))
    assert cache.load(key) is None  # no record: not an entry

    resumed = ThresholdMaskSource()
    keys = VoteCache(tmp_path / "cache", resumed).build_all(views, progress=False)
    assert resumed.calls == ["frame_002.png"]
    assert cache.get(2, views[2][1]).labels.shape == (2, 24, 32)
    assert keys[2] == key


def test_failed_write_leaves_no_entry_and_no_temp_file(tmp_path, monkeypatch):
    views = write_views(tmp_path / "images", count=1)
    cache = VoteCache(tmp_path / "cache", ThresholdMaskSource())

    def savez_then_crash(handle, **arrays):
        handle.write(b"PK\x03\x04 partial zip")
        raise OSError("disk full")

    monkeypatch.setattr(vote_cache_module.np, "savez", savez_then_crash)
    with pytest.raises(OSError, match="disk full"):
        cache.get(0, views[0][1])
    key = cache.view_key(views[0][1], 0)
    assert not cache.votes_path(key).exists()
    assert not any(".tmp-" in name for name in entry_files(cache))
    monkeypatch.undo()

    source = ThresholdMaskSource()
    assert VoteCache(tmp_path / "cache", source).get(0, views[0][1]).labels.shape == (2, 24, 32)
    assert source.calls == ["frame_000.png"]


@pytest.mark.parametrize("damage", ["truncate_labels", "garbage_record", "truncate_record", "ids_past_the_table"])
def test_damaged_entry_is_rebuilt_with_a_warning(tmp_path, damage):
    views = write_views(tmp_path / "images", count=1)
    VoteCache(tmp_path / "cache", ThresholdMaskSource()).build_all(views, progress=False)
    source = ThresholdMaskSource()
    cache = VoteCache(tmp_path / "cache", source)
    key = cache.view_key(views[0][1], 0)
    expected = np.array(np.load(cache.labels_path(key)))
    if damage == "truncate_labels":
        path = cache.labels_path(key)
        os.truncate(path, path.stat().st_size // 2)
    elif damage == "garbage_record":
        cache.votes_path(key).write_bytes(b"\x00" * 64)
    elif damage == "truncate_record":
        path = cache.votes_path(key)
        os.truncate(path, path.stat().st_size - 20)
    else:  # same shape and dtype, so only the ids tell: the first vote step would index past the centroid table
        labels = np.load(cache.labels_path(key))
        labels[1, 0, 0] = 7
        np.save(cache.labels_path(key), labels)

    with pytest.warns(UserWarning, match=r"is damaged .*; rebuilding it"):
        rebuilt = cache.get(0, views[0][1])
    assert source.calls == ["frame_000.png"]
    assert np.array_equal(np.asarray(rebuilt.labels), expected)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert VoteCache(tmp_path / "cache", ThresholdMaskSource()).load(key) is not None


def test_tampered_config_file_rebuilds(tmp_path):
    views = write_views(tmp_path / "images", count=1)
    cache = VoteCache(tmp_path / "cache", ThresholdMaskSource())
    cache.build_all(views, progress=False)
    (cache.entry_dir / "config.json").write_text('{"format_version": 0}')
    with pytest.warns(UserWarning, match="other arguments"):
        source = ThresholdMaskSource()
        VoteCache(tmp_path / "cache", source).build_all(views, progress=False)
    assert source.calls == ["frame_000.png"]


def test_damaged_entries_are_reported_once_and_counted(tmp_path):
    views = write_views(tmp_path / "images", count=3)
    keys = VoteCache(tmp_path / "cache", ThresholdMaskSource()).build_all(views, progress=False)
    cache = VoteCache(tmp_path / "cache", ThresholdMaskSource())
    for key in keys:
        labels = np.load(cache.labels_path(key))
        labels[0, -1, -1] = 60000
        np.save(cache.labels_path(key), labels)
    with pytest.warns(UserWarning) as caught:
        cache.build_all(views, progress=False)
    assert len([w for w in caught if "is damaged" in str(w.message)]) == 1
    assert "level 0 holds label ids 0..60000, outside its masks' ids 0..1" in str(caught[0].message)
    assert cache.rebuilt_damaged == 3 and cache.source.calls == ["frame_000.png", "frame_001.png", "frame_002.png"]


def test_nothing_is_written_until_an_entry_is_made(tmp_path):
    class Failing(ThresholdMaskSource):
        def masks_for_image(self, image, image_path, frame_index):
            raise ValueError("the mask source cannot start")

    views = write_views(tmp_path / "images", count=1)
    with pytest.raises(ValueError, match="cannot start"):
        VoteCache(tmp_path / "cache", Failing()).build_all(views, progress=False)
    assert not (tmp_path / "cache").exists()


class ThreadedThresholdSource(ThresholdMaskSource):
    """The same masks from a source that declares itself thread-safe; records the threads it ran on."""

    thread_safe = True

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.threads = set()

    def masks_for_image(self, image, image_path, frame_index):
        self.threads.add(threading.get_ident())
        if self.fail_on and Path(image_path).name == self.fail_on:
            raise ValueError(f"unreadable masks for {Path(image_path).name}")
        return super().masks_for_image(image, image_path, frame_index)


def test_thread_safe_sources_build_in_threads_with_the_same_entries(tmp_path):
    """A file-reading source builds views in worker threads: the same keys and entries as one at a time, and
    a view's error reaches the caller and leaves no entry for that view."""
    views = write_views(tmp_path / "images", count=6)
    sequential = VoteCache(tmp_path / "one", ThresholdMaskSource())
    keys = sequential.build_all(views, progress=False)
    threaded_source = ThreadedThresholdSource()
    threaded = VoteCache(tmp_path / "many", threaded_source)
    assert threaded.build_all(views, progress=False) == keys
    assert threading.get_ident() not in threaded_source.threads  # workers, not the caller's thread
    assert sorted(threaded_source.calls) == sorted(Path(path).name for _, path in views)
    for index, path in views:
        a, b = sequential.get(index, path), threaded.get(index, path)
        np.testing.assert_array_equal(a.labels, b.labels)
        for table_a, table_b in zip(a.centroids, b.centroids):
            np.testing.assert_array_equal(table_a, table_b)
    failing = VoteCache(tmp_path / "fail", ThreadedThresholdSource(fail_on="frame_003.png"))
    with pytest.raises(ValueError, match="frame_003.png"):
        failing.build_all(views, progress=False)
    assert failing.load(failing.view_key(views[3][1], 3)) is None
