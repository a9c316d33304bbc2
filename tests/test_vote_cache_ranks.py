"""A vote cache made by two CPU processes writing the one cache: the same entries as one process, and a rank that
dies mid-way keeps what was finished and leaves no half-written entry."""

from __future__ import annotations

import os
import signal
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


class DyingSamSource(SamMaskSource):
    """SAM that kills its own process (SIGKILL: no clean-up runs) when it reaches the image ``dies_on``."""

    def __init__(self, dies_on: str, **options):
        super().__init__(**options)
        self.dies_on = dies_on

    def masks_for_image(self, image, image_path, frame_index):
        if Path(image_path).name == self.dies_on:
            os.kill(os.getpid(), signal.SIGKILL)
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


def test_a_rank_that_dies_keeps_the_finished_entries_and_no_half_written_one(tmp_path, one_torch_thread):
    views = write_views(tmp_path / "images")
    # rank 1 makes views 1, 3, 5 in that order and dies on view 3: view 1 is finished, view 3 never is
    dying = DyingSamSource(dies_on="frame_003.png", sam_model=tiny_sam(), device="cpu", **SAM_OPTIONS)
    cache = VoteCache(tmp_path / "cache", dying)
    with pytest.raises(VoteSplatInputError) as caught:
        build_on_ranks(cache, views, ["cpu", "cpu"], progress=False)
    message = str(caught.value)
    assert "\n" not in message
    assert "rank 1 of 2 (cpu) stopped mid-way (killed by signal SIGKILL)" in message
    assert "run the command again to make the rest" in message and str(cache.entry_dir) in message

    keys = [cache.view_key(path, index) for index, path in views]
    assert cache.votes_path(keys[1]).is_file()  # finished before the kill: kept
    assert not cache.votes_path(keys[3]).exists() and not cache.labels_path(keys[3]).exists()
    assert leftovers(cache) == []
    made = [key for key in keys if cache.votes_path(key).is_file()]
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
    broken = tmp_path / "images" / "frame_003.png"  # rank 1's second view
    broken.write_bytes(b"not an image")
    cache = VoteCache(tmp_path / "cache", sam_source())
    with pytest.raises(VoteSplatInputError) as caught:
        build_on_ranks(cache, views, ["cpu", "cpu"], progress=False)
    message = str(caught.value)
    assert "\n" not in message and str(broken) in message and "(rank 1 of 2, cpu; the " in message
    assert leftovers(cache) == []


def test_votesplat_masks_on_two_cpu_processes_makes_the_one_process_cache(tmp_path):
    from conftest import DEMO_SCENE

    from votesplat_ns.cli.masks_cli import MasksConfig, main as make_masks

    one = make_masks(MasksConfig(data=DEMO_SCENE, cache_dir=tmp_path / "one"))
    two = make_masks(MasksConfig(data=DEMO_SCENE, cache_dir=tmp_path / "two", num_gpus=2, sam_device="cpu"))
    assert two["keys"] == one["keys"] and len(one["keys"]) == 34
    assert sorted(p.name for p in two["entry_dir"].iterdir()) == sorted(p.name for p in one["entry_dir"].iterdir())
    for key in one["keys"]:
        assert_same_entry_files(one["entry_dir"], two["entry_dir"], key)
