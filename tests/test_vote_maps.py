"""2D vote construction (paper Eq. 3-4): centroids, border filtering, overlap rule, resizing."""

import numpy as np
import pytest
import torch

from votesplat_ns.core.vote_maps import (
    VoteMaps,
    label_tensor,
    labels_from_binary_masks,
    mask_centroids,
    pixels_and_targets,
    resize_label_images,
    resize_vote_maps,
    round_half_away_from_zero,
    to_continuous,
    vote_maps_from_labels,
    voting_pixels,
)


def flat_labels(maps: VoteMaps) -> torch.Tensor:
    """A view's mask ids as training looks them up: [L, H*W]."""
    return torch.from_numpy(maps.labels.reshape(maps.labels.shape[0], -1).astype(np.int32))


def test_centroids_hand_computed_with_rounding_and_renumbering():
    labels = np.zeros((6, 8), dtype=np.int32)
    # id 9: columns {2, 3} on rows {2, 3}: mean column 2.5 -> 3 (banker's rounding would give 2),
    # mean row 2.5 -> 3
    labels[2:4, 2:4] = 9
    # id 4: pixels (x=1,y=4), (x=2,y=4), (x=4,y=4): mean column 7/3 -> 2, row 4
    labels[4, [1, 2, 4]] = 4
    labels_out, centroids = mask_centroids(labels, border_masks="drop")

    assert labels_out.dtype == np.int32 and centroids.dtype == np.float32
    # compact renumbering in increasing order of the input id: 4 -> 1, 9 -> 2
    assert np.array_equal(labels_out == 1, labels == 4)
    assert np.array_equal(labels_out == 2, labels == 9)
    assert centroids.shape == (3, 2)
    assert np.all(np.isnan(centroids[0]))
    np.testing.assert_array_equal(centroids[1], [2.0, 4.0])
    np.testing.assert_array_equal(centroids[2], [3.0, 3.0])


def test_rounding_rule_is_half_away_from_zero():
    values = np.array([0.5, 1.5, 2.5, 2.49, 3.5, -2.5, 7 / 3])
    np.testing.assert_array_equal(round_half_away_from_zero(values), [1, 2, 3, 2, 4, -3, 2])


def test_border_mask_rules():
    labels = np.zeros((5, 6), dtype=np.int32)
    labels[0:2, 2:4] = 1  # touches the top row
    labels[2:4, 2:4] = 2  # interior
    labels[2, 5] = 3  # touches the right column
    dropped, dropped_centroids = mask_centroids(labels, border_masks="drop")
    assert set(np.unique(dropped)) == {0, 1}
    assert np.array_equal(dropped == 1, labels == 2)
    np.testing.assert_array_equal(dropped_centroids[1], [3.0, 3.0])  # mean (2.5, 2.5) rounds up

    kept, kept_centroids = mask_centroids(labels, border_masks="vote")
    assert np.array_equal(kept, labels)
    np.testing.assert_array_equal(kept_centroids[1:], [[3.0, 1.0], [3.0, 3.0], [5.0, 2.0]])

    # mask_only: every mask stays a mask, only the interior one has a vote target
    masks, masks_centroids = mask_centroids(labels, border_masks="mask_only")
    assert np.array_equal(masks, labels)
    assert np.isnan(masks_centroids[[0, 1, 3]]).all()
    np.testing.assert_array_equal(masks_centroids[2], [3.0, 3.0])
    maps = vote_maps_from_labels([labels], border_masks="mask_only")
    votes, valid = maps.targets(0)
    assert np.array_equal(valid, labels == 2)
    _, _, valid_t = pixels_and_targets(
        torch.arange(labels.size), labels.shape[1], flat_labels(maps), torch.from_numpy(maps.padded_centroids()), 1.0
    )
    assert torch.equal(valid_t[:, 0], torch.from_numpy(labels == 2).reshape(-1))

    with pytest.raises(ValueError, match="border_masks must be one of"):
        mask_centroids(labels, border_masks="keep")


def test_empty_view_is_valid():
    labels_out, centroids = mask_centroids(np.zeros((4, 5), dtype=np.uint16))
    assert not labels_out.any()
    assert centroids.shape == (1, 2) and np.all(np.isnan(centroids))
    maps = vote_maps_from_labels([np.zeros((4, 5), dtype=np.int32)] * 2, level_names=("a", "b"))
    assert maps.labels.shape == (2, 4, 5) and maps.padded_centroids().shape == (2, 1, 2)
    votes, valid = maps.targets(1)
    assert not valid.any() and np.all(np.isnan(votes))


def test_overlap_rule_smaller_mask_wins_and_ties_go_to_the_earlier_mask():
    big = np.zeros((6, 6), dtype=bool)
    big[1:5, 1:5] = True
    small = np.zeros((6, 6), dtype=bool)
    small[2:4, 2:4] = True
    for order in ([big, small], [small, big]):
        labels = labels_from_binary_masks(order)
        small_id = 1 + [m is small for m in order].index(True)
        big_id = 1 + [m is big for m in order].index(True)
        assert np.all(labels[small] == small_id)
        assert np.all(labels[big & ~small] == big_id)
        assert np.all(labels[~big] == 0)

    left = np.zeros((4, 4), dtype=bool)
    left[1:3, 0:2] = True
    right = np.zeros((4, 4), dtype=bool)
    right[1:3, 1:3] = True  # same area, overlaps 'left' in column 1
    assert np.all(labels_from_binary_masks([left, right])[1:3, 1] == 1)
    assert np.all(labels_from_binary_masks([right, left])[1:3, 1] == 1)


def test_labels_from_binary_masks_errors():
    with pytest.raises(ValueError, match="shape"):
        labels_from_binary_masks([])
    assert labels_from_binary_masks([], shape=(2, 3)).shape == (2, 3)
    with pytest.raises(ValueError, match="shape"):
        labels_from_binary_masks([np.zeros((2, 2), bool), np.zeros((3, 2), bool)])
    with pytest.raises(ValueError, match="integer"):
        mask_centroids(np.zeros((3, 3), dtype=np.float32))
    with pytest.raises(ValueError, match="negative"):
        mask_centroids(-np.ones((3, 3), dtype=np.int32))


def test_targets_in_index_and_continuous_frames():
    labels = np.zeros((5, 5), dtype=np.int32)
    labels[1:4, 1:3] = 1
    maps = vote_maps_from_labels([labels])
    votes, valid = maps.targets(0)
    assert votes.shape == (5, 5, 2) and valid.dtype == bool
    np.testing.assert_array_equal(votes[valid], np.tile([2.0, 2.0], (6, 1)))  # mean (1.5, 2) -> (2, 2)
    continuous, valid_c = maps.targets_continuous(0)
    np.testing.assert_array_equal(continuous[valid_c], np.tile([2.5, 2.5], (6, 1)))
    assert np.array_equal(to_continuous(np.array([0.0])), [0.5])

    # the training lookup of every pixel: its 2D vote in the continuous frame, where the pixel carries one
    _, targets, valid_t = pixels_and_targets(
        torch.arange(labels.size), 5, flat_labels(maps), torch.from_numpy(maps.padded_centroids()), 1.0
    )
    assert targets.shape == (25, 1, 2)
    assert torch.equal(valid_t[:, 0], torch.from_numpy(valid).reshape(-1))
    np.testing.assert_array_equal(targets[:, 0][valid_t[:, 0]].numpy(), continuous[valid])


def test_padded_centroids_pad_with_nan():
    a = np.zeros((6, 6), dtype=np.int32)
    a[1:3, 1:3] = 1
    a[3:5, 3:5] = 2
    b = np.zeros((6, 6), dtype=np.int32)
    b[2:4, 2:4] = 1
    maps = vote_maps_from_labels([a, b])
    padded = maps.padded_centroids()
    assert padded.shape == (2, 3, 2) and padded.dtype == np.float32
    np.testing.assert_array_equal(padded[0, 1:], maps.centroids[0][1:])
    assert np.all(np.isnan(padded[1, 2])) and np.all(np.isnan(padded[:, 0]))


def test_resize_keeps_centroids_on_the_same_spot():
    labels = np.zeros((9, 11), dtype=np.int32)
    labels[2:5, 3:8] = 1  # mean column 5, mean row 3: integral, so no rounding
    labels[5:8, 1:3] = 2
    maps = vote_maps_from_labels([labels])
    np.testing.assert_array_equal(maps.centroids[0][1], [5.0, 3.0])

    up = resize_vote_maps(maps, 18, 22)
    assert up.labels.shape == (1, 18, 22) and up.labels.dtype == maps.labels.dtype
    # nearest-neighbour x2 upsampling duplicates every pixel
    assert np.array_equal(up.labels[0], np.repeat(np.repeat(maps.labels[0], 2, axis=0), 2, axis=1))
    # the rescaled centroid equals the exact mean position of the upsampled mask: (c + 0.5) * 2 - 0.5
    rows, cols = np.nonzero(up.labels[0] == 1)
    np.testing.assert_allclose(up.centroids[0][1], [cols.mean(), rows.mean()])
    np.testing.assert_allclose(up.centroids[0][1], [10.5, 6.5])

    # and back again: the same labels and centroids
    back = resize_vote_maps(up, 9, 11)
    assert np.array_equal(back.labels, maps.labels)
    np.testing.assert_allclose(back.centroids[0][1:], maps.centroids[0][1:], atol=1e-5)

    # non-integer factor: in the continuous frame the centroid scales by new/old per axis
    odd = resize_vote_maps(maps, 6, 7)
    np.testing.assert_allclose((odd.centroids[0][1:] + 0.5), (maps.centroids[0][1:] + 0.5) * [7 / 11, 6 / 9], rtol=1e-6)
    assert resize_vote_maps(maps, 9, 11) is maps


def test_nearest_downsample_samples_the_covering_pixel():
    labels = np.arange(24, dtype=np.int32).reshape(4, 6)
    np.testing.assert_array_equal(resize_label_images(labels, 2, 3), labels[1::2, 1::2])
    with pytest.raises(ValueError, match="positive"):
        resize_vote_maps(vote_maps_from_labels([labels]), 0, 3)


def test_vote_maps_validation():
    with pytest.raises(ValueError, match=r"\[L, H, W\]"):
        VoteMaps(labels=np.zeros((4, 4), np.uint16), centroids=[])
    with pytest.raises(ValueError, match="centroid tables"):
        VoteMaps(labels=np.zeros((2, 4, 4), np.uint16), centroids=[np.full((1, 2), np.nan)])
    many = np.arange(70000, dtype=np.int64).reshape(1, 70000) % 70000 + 1
    padded = np.zeros((3, 70002), dtype=np.int64)
    padded[1, 1:-1] = many
    assert vote_maps_from_labels([padded], border_masks="vote").labels.dtype == np.int32


def test_huge_sparse_ids_are_renumbered_without_a_huge_table():
    labels = np.zeros((6, 6), dtype=np.int64)
    labels[1:3, 1:3] = 2**40
    labels[3:5, 3:5] = 7
    labels_out, centroids = mask_centroids(labels)
    assert np.array_equal(labels_out == 1, labels == 7) and np.array_equal(labels_out == 2, labels == 2**40)
    np.testing.assert_array_equal(centroids[1:], [[4.0, 4.0], [2.0, 2.0]])


def test_compact_label_tensor_widens_past_int16():
    """A view with more than 32767 masks in a level keeps int32 labels (int16 would wrap them)."""
    labels = np.zeros((2, 4, 4), dtype=np.int32)
    labels[1, 0, 0] = 32767
    assert label_tensor(labels).dtype == torch.int16
    labels[1, 0, 1] = 32768
    wide = label_tensor(labels)
    assert wide.dtype == torch.int32 and int(wide.max()) == 32768
    assert label_tensor(labels.astype(np.uint16)).dtype == torch.int32  # the vote cache's uint16, widened


def test_voting_pixels_are_int32_flat_indices():
    """The pixels with a vote at some level, as int32 row * W + column (half of int64's bytes per view)."""
    labels = torch.tensor([[[0, 1, 1], [2, 0, 0]], [[0, 0, 3], [0, 0, 1]]], dtype=torch.int16)
    centroids = torch.full((2, 4, 2), float("nan"))
    centroids[0, 1] = torch.tensor([1.0, 0.0])  # level 0: mask 1 votes, mask 2 has no vote
    centroids[1, 3] = torch.tensor([2.0, 0.0])  # level 1: mask 3 votes, mask 1 has no vote
    voting = voting_pixels(labels, centroids)
    assert voting.dtype == torch.int32 and voting.tolist() == [1, 2]
