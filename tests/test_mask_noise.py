import numpy as np
import pytest
from scipy import ndimage

from votesplat_ns.eval.mask_noise import MaskNoise, dilate, erode


def _scene_labels(dtype=np.uint16):
    """40x48 label image: masks 1 and 2 touch, 3 is 2 px from 2, 4 and 5 are far from everything."""
    labels = np.zeros((40, 48), dtype=dtype)
    labels[5:15, 5:15] = 1
    labels[5:15, 15:25] = 2  # shares an edge with 1
    labels[5:15, 27:35] = 3  # gap of 2 columns to mask 2
    labels[25:35, 5:12] = 4
    yy, xx = np.mgrid[0:40, 0:48]
    labels[(yy - 30) ** 2 + (xx - 36) ** 2 <= 16] = 5
    return labels


def _masks(labels):
    return {int(v): labels == v for v in np.unique(labels) if v > 0}


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int32, np.int64])
def test_rate_zero_is_identity(dtype):
    labels = _scene_labels(dtype)
    noisy, events = MaskNoise(seed=3).apply_with_events(labels, view_index=5)
    assert noisy.dtype == labels.dtype
    assert np.array_equal(noisy, labels)
    assert noisy is not labels
    assert events == []


def test_drop_removes_whole_masks_only():
    labels = _scene_labels()
    assert not MaskNoise(drop_rate=1.0).apply(labels).any()
    noise = MaskNoise(drop_rate=0.5, seed=1)
    dropped_counts = set()
    for view in range(6):
        noisy, events = noise.apply_with_events(labels, view)
        dropped = {e.label for e in events}
        assert all(e.kind == "drop" for e in events)
        for label, mask in _masks(labels).items():
            if label in dropped:
                assert not (noisy == label).any() and not noisy[mask].any()
            else:
                assert np.array_equal(noisy == label, mask)
        dropped_counts.add(len(dropped))
    assert len(dropped_counts) > 1  # some views lose more masks than others


def test_merge_joins_touching_or_near_masks_only():
    labels = _scene_labels()
    original = _masks(labels)
    noisy, events = MaskNoise(merge_rate=1.0, merge_max_gap_px=2, seed=0).apply_with_events(labels)
    merges = [(e.label, e.other) for e in events]
    assert merges and all(e.kind == "merge" for e in events)
    involved = [m for pair in merges for m in pair]
    assert len(involved) == len(set(involved))  # each mask merges at most once
    for keep, gone in merges:
        assert {keep, gone} <= {1, 2, 3}  # 4 and 5 have no neighbour within 2 px
        assert np.array_equal(noisy == keep, original[keep] | original[gone])
        assert not (noisy == gone).any()
    assert np.array_equal(noisy == 4, original[4]) and np.array_equal(noisy == 5, original[5])
    assert np.array_equal(noisy > 0, labels > 0)  # merging never moves a pixel's mask/no-mask state
    # with a gap of 1 (touching only), mask 3 can never be absorbed or absorb
    for seed in range(5):
        _, events = MaskNoise(merge_rate=1.0, merge_max_gap_px=1, seed=seed).apply_with_events(labels)
        assert all({e.label, e.other} == {1, 2} for e in events)


def test_split_cuts_each_mask_along_a_line():
    labels = _scene_labels()
    original = _masks(labels)
    noisy, events = MaskNoise(split_rate=1.0, seed=7).apply_with_events(labels.astype(np.int32), view_index=2)
    assert sorted(e.label for e in events) == [1, 2, 3, 4, 5]
    new_ids = [e.other for e in events]
    assert len(set(new_ids)) == 5 and min(new_ids) > labels.max()
    for e in events:
        kept, new = noisy == e.label, noisy == e.other
        assert kept.any() and new.any()
        assert np.array_equal(kept | new, original[e.label])
        nx, ny, c = e.line
        ys, xs = np.nonzero(new)
        assert np.all(nx * xs + ny * ys > c)
        ys, xs = np.nonzero(kept)
        assert np.all(nx * xs + ny * ys <= c)
    assert len(np.unique(noisy)) - 1 == 10


def test_split_needs_a_wide_enough_dtype():
    labels = np.zeros((4, 4), dtype=np.uint8)
    labels[:, :2] = 255
    with pytest.raises(ValueError, match="wider label dtype"):
        MaskNoise(split_rate=1.0).apply(labels)


@pytest.mark.parametrize("max_px", [1, 2])
def test_jitter_grows_or_shrinks_by_whole_pixels(max_px):
    square = np.ones((3, 3), dtype=bool)
    seen = set()
    for seed in range(12):
        labels = np.zeros((30, 30), dtype=np.int32)
        labels[8:20, 10:22] = 6
        noisy, events = MaskNoise(jitter_rate=1.0, max_jitter_px=max_px, seed=seed).apply_with_events(labels)
        (event,) = events
        r = abs(event.amount)
        assert 1 <= r <= max_px
        mask = labels == 6
        if event.amount > 0:
            expected = ndimage.binary_dilation(mask, structure=square, iterations=r)
        else:
            expected = ndimage.binary_erosion(mask, structure=square, iterations=r, border_value=1)
        assert np.array_equal(noisy == 6, expected)
        seen.add(event.amount)
    assert any(a > 0 for a in seen) and any(a < 0 for a in seen)


def test_jitter_dilation_covers_neighbours_and_erosion_leaves_background():
    labels = np.zeros((10, 12), dtype=np.int32)
    labels[2:8, 2:6] = 1
    labels[2:8, 6:10] = 2
    one, two = labels == 1, labels == 2
    outcomes = {}
    for seed in range(60):
        noisy, events = MaskNoise(jitter_rate=0.5, max_jitter_px=1, seed=seed).apply_with_events(labels)
        if [(e.label, e.amount) for e in events] in ([(1, 1)], [(1, -1)]):
            outcomes[events[0].amount] = noisy
    assert set(outcomes) == {1, -1}
    grown = outcomes[1]
    assert np.array_equal(grown == 1, dilate(one, 1))  # the growth covers the neighbour's first column
    assert np.array_equal(grown == 2, two & ~dilate(one, 1))
    shrunk = outcomes[-1]
    assert np.array_equal(shrunk == 1, erode(one, 1))
    assert np.array_equal(shrunk == 2, two)  # the neighbour does not take the freed pixels
    assert (shrunk[one & ~erode(one, 1)] == 0).all()


def test_erosion_ignores_the_image_border():
    labels = np.zeros((8, 8), dtype=np.int32)
    labels[:, :4] = 1  # touches the top, bottom and left borders
    assert np.array_equal(erode(labels == 1, 1), np.pad(np.ones((8, 3), bool), ((0, 0), (0, 5))))
    assert np.array_equal(dilate(labels == 1, 2), np.pad(np.ones((8, 6), bool), ((0, 0), (0, 2))))


def test_deterministic_per_seed_and_view():
    labels = _scene_labels()
    noise = MaskNoise(split_rate=0.5, merge_rate=0.5, jitter_rate=0.5, drop_rate=0.2, seed=11)
    a = [noise.apply(labels, view_index=v) for v in range(8)]
    b = noise.apply_to_views([labels] * 8)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not all(np.array_equal(a[0], x) for x in a[1:])
    other_seed = MaskNoise(split_rate=0.5, merge_rate=0.5, jitter_rate=0.5, drop_rate=0.2, seed=12)
    assert not all(np.array_equal(x, other_seed.apply(labels, view_index=v)) for v, x in enumerate(a))


def test_kinds_use_independent_streams():
    """Turning jitter on must not change which masks get dropped."""
    labels = _scene_labels()
    for view in range(5):
        _, only_drop = MaskNoise(drop_rate=0.5, seed=4).apply_with_events(labels, view)
        _, with_jitter = MaskNoise(drop_rate=0.5, jitter_rate=0.5, seed=4).apply_with_events(labels, view)
        assert [e for e in only_drop] == [e for e in with_jitter if e.kind == "drop"]


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(split_rate=1.5), "split_rate"),
        (dict(drop_rate=-0.1), "drop_rate"),
        (dict(merge_rate=float("nan")), "merge_rate"),
        (dict(jitter_rate="a lot"), "jitter_rate"),
        (dict(max_jitter_px=0), "max_jitter_px"),
        (dict(merge_max_gap_px=0), "merge_max_gap_px"),
    ],
)
def test_bad_parameters(kwargs, message):
    with pytest.raises(ValueError, match=message):
        MaskNoise(**kwargs)


@pytest.mark.parametrize(
    "labels, message",
    [
        (np.zeros((4, 4), dtype=np.float32), "integer"),
        (np.full((4, 4), -1), "negative"),
        (np.zeros((2, 4, 4), dtype=np.int32), "2D"),
    ],
)
def test_bad_labels(labels, message):
    with pytest.raises(ValueError, match=message):
        MaskNoise(drop_rate=0.5).apply(labels)
