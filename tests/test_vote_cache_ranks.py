"""A vote cache made by two ranks writing the one cache (rank 0 a thread of the test's process, rank 1 a CPU
process): the same entries as one process, the views handed out as the ranks ask, and a rank that stops mid-way
(killed, an error, Ctrl-C) keeps what was finished and leaves no half-written entry."""

from __future__ import annotations

import multiprocessing
import os
import re
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from test_mask_sources import tiny_sam

from votesplat_ns.core.mask_sources import SamMaskSource
from votesplat_ns.core.ply_io import TEMP_MARKER
from votesplat_ns.core.vote_cache import VoteCache
from votesplat_ns.core.vote_cache_ranks import build_on_ranks, rank_share
from votesplat_ns.errors import VoteSplatInputError

# the generator's filters at zero: the random model's masks survive (as in test_mask_sources)
SAM_OPTIONS = dict(
    points_per_side=3, pred_iou_thresh=0.0, stability_score_thresh=0.0, crop_n_layers=0, min_mask_region_area=0
)
NUM_VIEWS = 6


def write_views(folder: Path, count: int = NUM_VIEWS) -> list:
    """Small images of a few coloured blocks that move from view to view."""
    folder.mkdir(parents=True, exist_ok=True)
    views = []
    for i in range(count):
        image = np.full((24, 32, 3), 40, dtype=np.uint8)
        image[2 + i : 12 + i, 3 + i : 13 + i] = (220, 30, 30)
        image[8:20, 14 + i // 2 : 29] = (30, 200, 60)
        path = folder / f"frame_{i:03d}.png"
        Image.fromarray(image).save(path)
        views.append((i, path))
    return views


def sam_source() -> SamMaskSource:
    return SamMaskSource(sam_model=tiny_sam(), device="cpu", **SAM_OPTIONS)


def wait_for(pattern: str, folder: Path, seconds: float = 120.0) -> None:
    deadline = time.time() + seconds
    while not list(folder.glob(pattern)) and time.time() < deadline:
        time.sleep(0.05)


class RecordingSamSource(SamMaskSource):
    """SAM that notes in ``record_dir`` which process takes each image (``<image>.<pid>``), and makes the ranks'
    processes (not the test's, rank 0's) wait ``process_delay`` seconds per image."""

    def __init__(self, record_dir: Path, process_delay: float = 0.0, **options):
        super().__init__(**options)
        self.record_dir, self.process_delay, self.parent_pid = Path(record_dir), process_delay, os.getpid()

    def masks_for_image(self, image, image_path, frame_index):
        (self.record_dir / f"{Path(image_path).name}.{os.getpid()}").touch()
        if os.getpid() != self.parent_pid:
            time.sleep(self.process_delay)
        return super().masks_for_image(image, image_path, frame_index)


class DyingSamSource(SamMaskSource):
    """SAM that kills rank 1's process (SIGKILL: no clean-up runs) at its second image; rank 0 (the test's
    process) makes its first image only once that happened, so rank 1 surely takes two views. One view at a time,
    so that the first is written before the second starts."""

    overlaps_views = False

    def __init__(self, record_dir: Path, **options):
        super().__init__(**options)
        self.record_dir, self.parent_pid, self.images = Path(record_dir), os.getpid(), 0

    def masks_for_image(self, image, image_path, frame_index):
        name = Path(image_path).name
        if os.getpid() == self.parent_pid:
            wait_for("died-*", self.record_dir)
        else:
            self.images += 1
            if self.images == 2:
                (self.record_dir / f"died-{name}").touch()
                os.kill(os.getpid(), signal.SIGKILL)
            (self.record_dir / f"made-{name}").touch()
        return super().masks_for_image(image, image_path, frame_index)


class InterruptingSamSource(SamMaskSource):
    """SAM that, in the test's process, sends that process SIGINT (the user's Ctrl-C) at its second image."""

    def __init__(self, **options):
        super().__init__(**options)
        self.parent_pid, self.images = os.getpid(), 0

    def masks_for_image(self, image, image_path, frame_index):
        if os.getpid() == self.parent_pid:
            self.images += 1
            if self.images == 2:
                os.kill(os.getpid(), signal.SIGINT)  # Python raises KeyboardInterrupt in the main thread
        return super().masks_for_image(image, image_path, frame_index)


def assert_same_entry(a: VoteCache, b: VoteCache, key: str) -> None:
    assert_same_entry_files(a.entry_dir, b.entry_dir, key)


def assert_same_entry_files(a: Path, b: Path, key: str) -> None:
    """The entry ``key`` of entry folders ``a`` and ``b``: the same labels file, the same record (its zip's dates aside)."""
    assert (a / f"{key}.labels.npy").read_bytes() == (b / f"{key}.labels.npy").read_bytes()
    with np.load(a / f"{key}.votes.npz") as first, np.load(b / f"{key}.votes.npz") as second:
        assert sorted(first.files) == sorted(second.files)
        for name in first.files:
            x, y = first[name], second[name]
            assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), name


def leftovers(cache: VoteCache) -> list:
    """Temporary files, and labels files without their record (half an entry)."""
    names = [path.name for path in cache.entry_dir.iterdir()]
    orphans = [n for n in names if n.endswith(".labels.npy") and n.replace(".labels.npy", ".votes.npz") not in names]
    return [n for n in names if TEMP_MARKER in n] + orphans


def test_rank_share_takes_every_nth_view():
    assert rank_share(list(range(7)), 0, 3) == [0, 3, 6]
    assert rank_share(list(range(7)), 2, 3) == [2, 5]
    with pytest.raises(ValueError, match="outside"):
        rank_share([1, 2], 2, 2)


def test_two_processes_make_the_entries_one_process_makes(tmp_path, one_torch_thread):
    views = write_views(tmp_path / "images")
    one = VoteCache(tmp_path / "one", sam_source())
    keys = one.build_all(views, progress=False)
    assert any(int(np.asarray(one.load(key).labels).max()) > 0 for key in keys)  # masks, not empty label images

    two = VoteCache(tmp_path / "two", sam_source())
    assert two.entry_dir.name == one.entry_dir.name  # the same configuration, whatever the processes
    assert build_on_ranks(two, views, ["cpu", "cpu"], progress=False) == keys
    assert sorted(p.name for p in two.entry_dir.iterdir()) == sorted(p.name for p in one.entry_dir.iterdir())
    assert (two.entry_dir / "config.json").read_bytes() == (one.entry_dir / "config.json").read_bytes()
    for key in keys:
        assert_same_entry(one, two, key)
    assert leftovers(two) == []


def test_the_views_go_to_the_rank_that_is_free(tmp_path, one_torch_thread):
    """Rank 0 makes entries while rank 1's process starts; a slow rank makes fewer than its half."""
    views = write_views(tmp_path / "images")
    record = tmp_path / "record"
    record.mkdir()
    source = RecordingSamSource(record, process_delay=2.0, sam_model=tiny_sam(), device="cpu", **SAM_OPTIONS)
    cache = VoteCache(tmp_path / "cache", source)
    reference = VoteCache(tmp_path / "reference", sam_source())
    keys = reference.build_all(views, progress=False)
    assert cache.entry_dir.name == reference.entry_dir.name
    assert build_on_ranks(cache, views, ["cpu", "cpu"], progress=False) == keys

    takers = [path.name.rsplit(".", 1) for path in record.iterdir()]
    assert sorted(name for name, _ in takers) == sorted(path.name for _, path in views)  # each view taken once
    by_rank_0 = sum(1 for _, pid in takers if int(pid) == os.getpid())
    assert by_rank_0 > NUM_VIEWS // 2  # more than the fixed share r, r + N, ... would give it
    for key in keys:
        assert_same_entry(reference, cache, key)
    assert leftovers(cache) == []


def test_a_source_that_reads_files_makes_several_views_per_take_in_threads(tmp_path, monkeypatch):
    from votesplat_ns.core.mask_sources import FolderMaskSource
    from votesplat_ns.core.vote_cache import BUILD_THREADS

    views = write_views(tmp_path / "images", count=12)
    (tmp_path / "masks" / "instance").mkdir(parents=True)
    for _, path in views:
        labels = (np.asarray(Image.open(path))[..., 0] > 100).astype(np.uint8)
        Image.fromarray(labels).save(tmp_path / "masks" / "instance" / path.name)
    takes: list = []
    build_all = VoteCache.build_all

    def recorded(self, views_taken, *args, **kwargs):  # rank 0's takes (the ranks' processes do not see this)
        takes.append(len(views_taken))
        return build_all(self, views_taken, *args, **kwargs)

    monkeypatch.setattr(VoteCache, "build_all", recorded)
    cache = VoteCache(tmp_path / "cache", FolderMaskSource(tmp_path / "masks"))
    keys = build_on_ranks(cache, views, ["cpu", "cpu"], progress=False)
    assert takes and max(takes) > 1 and max(takes) <= BUILD_THREADS  # several views at a time, as one process
    reference = VoteCache(tmp_path / "reference", FolderMaskSource(tmp_path / "masks"))
    assert build_all(reference, views, progress=False) == keys
    for key in keys:
        assert_same_entry(reference, cache, key)
    assert leftovers(cache) == []


def test_a_rank_that_dies_keeps_the_finished_entries_and_no_half_written_one(tmp_path, one_torch_thread):
    views = write_views(tmp_path / "images")
    record = tmp_path / "record"
    record.mkdir()
    # rank 1 finishes its first view and dies on its second; rank 0 finishes the view it holds and stops
    dying = DyingSamSource(record, sam_model=tiny_sam(), device="cpu", **SAM_OPTIONS)
    cache = VoteCache(tmp_path / "cache", dying)
    with pytest.raises(VoteSplatInputError) as caught:
        build_on_ranks(cache, views, ["cpu", "cpu"], progress=False)
    message = str(caught.value)
    assert "\n" not in message
    assert "rank 1 of 2 (cpu) stopped mid-way (killed by signal SIGKILL)" in message
    assert "run the command again to make the rest" in message and str(cache.entry_dir) in message

    keys = [cache.view_key(path, index) for index, path in views]
    key_of = {path.name: key for (_, path), key in zip(views, keys)}
    (finished,) = [key_of[path.name.removeprefix("made-")] for path in record.glob("made-*")]
    (killed,) = [key_of[path.name.removeprefix("died-")] for path in record.glob("died-*")]
    assert cache.votes_path(finished).is_file()  # finished before the kill: kept
    assert not cache.votes_path(killed).exists() and not cache.labels_path(killed).exists()
    assert leftovers(cache) == []
    made = [key for key in keys if cache.votes_path(key).is_file()]
    assert len(made) >= 2  # rank 1's first view and the one rank 0 held
    assert f"the {len(made)} of {NUM_VIEWS} vote maps made so far are kept" in message

    # what was kept is what one process makes; building again makes only the rest
    reference = VoteCache(tmp_path / "reference", sam_source())
    assert reference.build_all(views, progress=False) == keys
    for key in made:
        assert_same_entry(reference, cache, key)
    resumed = VoteCache(tmp_path / "cache", sam_source())
    stamps = {key: resumed.votes_path(key).stat().st_mtime_ns for key in made}
    assert build_on_ranks(resumed, views, ["cpu", "cpu"], progress=False) == keys
    assert {key: resumed.votes_path(key).stat().st_mtime_ns for key in made} == stamps
    for key in keys:
        assert_same_entry(reference, resumed, key)
    assert leftovers(resumed) == []


def test_bad_input_met_by_a_rank_is_one_line_naming_the_file(tmp_path, one_torch_thread):
    views = write_views(tmp_path / "images", count=4)
    broken = tmp_path / "images" / "frame_003.png"
    broken.write_bytes(b"not an image")
    cache = VoteCache(tmp_path / "cache", sam_source())
    with pytest.raises(VoteSplatInputError) as caught:
        build_on_ranks(cache, views, ["cpu", "cpu"], progress=False)
    message = str(caught.value)
    assert "\n" not in message and str(broken) in message and re.search(r"\(rank [01] of 2, cpu; the ", message)
    assert leftovers(cache) == []


def test_an_error_in_rank_0_is_one_line_and_leaves_no_half_written_entry(tmp_path, one_torch_thread, monkeypatch):
    """Rank 0 (this process's thread) fails between an entry's labels file and its record: the labels file goes."""
    views = write_views(tmp_path / "images")
    cache = VoteCache(tmp_path / "cache", sam_source())
    half_written = []

    def failing_savez(handle, **arrays):  # in this process only: rank 1's process has its own numpy
        half_written.extend(cache.entry_dir.glob("*.labels.npy"))
        handle.write(b"PK\x03\x04 the start of a record")
        raise RuntimeError("the disk went away")

    monkeypatch.setattr(np, "savez", failing_savez)
    with pytest.raises(VoteSplatInputError) as caught:
        build_on_ranks(cache, views, ["cpu", "cpu"], progress=False)
    monkeypatch.undo()
    message = str(caught.value)
    assert "\n" not in message
    assert "rank 0 of 2 (cpu) stopped mid-way (RuntimeError: the disk went away)" in message
    assert "run the command again to make the rest" in message
    assert half_written and not any(path.exists() for path in half_written)
    assert leftovers(cache) == []
    assert not [thread for thread in threading.enumerate() if thread.name == "votesplat-rank-0"]
    assert not multiprocessing.active_children()


def test_ctrl_c_stops_both_ranks_and_keeps_the_finished_entries(tmp_path, one_torch_thread):
    views = write_views(tmp_path / "images")
    source = InterruptingSamSource(sam_model=tiny_sam(), device="cpu", **SAM_OPTIONS)
    cache = VoteCache(tmp_path / "cache", source)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # pytest in the background ignores it
    try:
        with pytest.raises(KeyboardInterrupt):
            build_on_ranks(cache, views, ["cpu", "cpu"], progress=False)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert not [thread for thread in threading.enumerate() if thread.name == "votesplat-rank-0"]
    assert not multiprocessing.active_children()
    assert leftovers(cache) == []
    keys = [cache.view_key(path, index) for index, path in views]
    made = [key for key in keys if cache.votes_path(key).is_file()]
    assert len(made) >= 2  # rank 0's first view, and the second, under way at the Ctrl-C, finished
    reference = VoteCache(tmp_path / "reference", sam_source())
    assert reference.build_all(views, progress=False) == keys
    for key in made:
        assert_same_entry(reference, cache, key)


def test_votesplat_masks_on_two_cpu_processes_makes_the_one_process_cache(tmp_path):
    from conftest import DEMO_SCENE

    from votesplat_ns.cli.masks_cli import MasksConfig, main as make_masks

    one = make_masks(MasksConfig(data=DEMO_SCENE, cache_dir=tmp_path / "one"))
    two = make_masks(MasksConfig(data=DEMO_SCENE, cache_dir=tmp_path / "two", num_gpus=2, sam_device="cpu"))
    assert two["keys"] == one["keys"] and len(one["keys"]) == 34
    assert sorted(p.name for p in two["entry_dir"].iterdir()) == sorted(p.name for p in one["entry_dir"].iterdir())
    for key in one["keys"]:
        assert_same_entry_files(one["entry_dir"], two["entry_dir"], key)


def test_rank_devices_give_each_gpu_its_processes_and_refuse_what_the_machine_lacks_in_one_line(monkeypatch):
    import torch

    from votesplat_ns.ns.masks import rank_devices

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert rank_devices(1, None) == [] and rank_devices(1, "cuda:1") == []  # one process, on --sam-device
    assert rank_devices(2, None) == ["cuda:0", "cuda:1"]
    assert rank_devices(2, None, 2) == ["cuda:0", "cuda:1", "cuda:0", "cuda:1"]  # rank 0, this process, on cuda:0
    assert rank_devices(1, None, 2) == ["cuda:0", "cuda:0"]
    assert rank_devices(1, "cuda:1", 3) == ["cuda:1"] * 3
    assert rank_devices(3, "cpu") == ["cpu"] * 3
    refused = {
        (1, None, 0): "--processes-per-gpu 0: give 1 or more processes per GPU",
        (2, "cpu", 2): "--processes-per-gpu 2 shares a GPU, and --sam-device cpu runs on the CPU",
        (3, None, 2): "--num-gpus 3 --processes-per-gpu 2: this machine has 2 GPUs; give --num-gpus 2 or less",
        (3, None, 1): "--num-gpus 3: this machine has 2 GPUs",
        (1, "cuda:2", 2): "SAM device 'cuda:2': this machine has 2 GPUs",
        (2, "cuda:1", 2): "--sam-device cuda:1 names one device",
    }
    for args, needle in refused.items():
        with pytest.raises(VoteSplatInputError, match=re.escape(needle)):
            rank_devices(*args)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)
    with pytest.raises(VoteSplatInputError, match=re.escape("CUDA is not available); leave --processes-per-gpu at 1")):
        rank_devices(1, None, 2)
