import numpy as np
import pytest
import torch
from PIL import Image

from votesplat_ns.core.cameras import PinholeView
from votesplat_ns.core.rasterize_torch import rasterize_torch
from votesplat_ns.eval.evaluation import (
    average_precision_3d,
    check_reconstruction,
    contingency,
    flat_image_psnr,
    gaussian_purity,
    instance_palette,
    match_instances,
    object_scores,
    psnr,
    save_comparison_png,
)
from votesplat_ns.eval.ground_truth import score_level
from votesplat_ns.eval.removal import ghost_fractions, mean_ghost_percent


def _two_views():
    """Two 6x8 views with three GT instances; instance 3 only appears in view 1."""
    v0 = np.zeros((6, 8), dtype=np.uint16)
    v0[1:3, 1:4] = 1  # 6 px
    v0[3:6, 5:8] = 2  # 9 px
    v1 = np.zeros((6, 8), dtype=np.uint16)
    v1[0:2, 0:2] = 1  # 4 px
    v1[2:6, 2:4] = 2  # 8 px
    v1[4:6, 6:8] = 3  # 4 px
    return [v0, v1]


def test_perfect_prediction():
    gt = _two_views()
    scores = match_instances(gt, [g.astype(np.int32) for g in gt])
    assert scores.miou == 1.0
    assert scores.precision == 1.0 and scores.recall == 1.0 and scores.f1 == 1.0
    assert scores.matches == {1: 1, 2: 2, 3: 3}


def test_swapped_ids_are_perfect_after_matching():
    gt = _two_views()
    relabel = np.array([-1, 7, 3, 12])  # 0 -> -1 (none), 1 -> 7, 2 -> 3, 3 -> 12
    pred = [relabel[g] for g in gt]
    scores = match_instances(gt, pred)
    assert scores.miou == 1.0
    assert scores.matches == {1: 7, 2: 3, 3: 12}
    assert scores.precision == 1.0 and scores.recall == 1.0


def test_merged_instances():
    gt = _two_views()
    pred = [np.where(g > 0, np.where(g == 3, 9, 5), 0) for g in gt]  # 1 and 2 merged into 5
    scores = match_instances(gt, pred)
    area1, area2 = 6 + 4, 9 + 8
    # the merged prediction goes to instance 2 (IoU 17/27 beats 10/27); instance 1 is left unmatched
    assert scores.matches == {1: None, 2: 5, 3: 9}
    assert scores.per_gt_iou[2] == pytest.approx(area2 / (area1 + area2))
    assert scores.per_gt_iou[1] == 0.0
    assert scores.miou == pytest.approx((0.0 + area2 / (area1 + area2) + 1.0) / 3)
    assert scores.true_positives == 2  # 17/27 = 0.63 >= 0.5, and instance 3
    assert scores.precision == pytest.approx(2 / 2)
    assert scores.recall == pytest.approx(2 / 3)


def test_split_instance():
    gt = _two_views()
    pred = [g.astype(np.int64) for g in gt]
    # instance 2 split into ids 2 (first column of each view's block) and 8 (the rest)
    pred[0][3:6, 6:8] = 8  # 6 of its 9 px in view 0
    pred[1][2:6, 3:4] = 8  # 4 of its 8 px in view 1
    scores = match_instances(gt, pred)
    assert scores.matches[2] == 8  # 10 px of 17 beats 7 of 17
    assert scores.per_gt_iou[2] == pytest.approx(10 / 17)
    assert scores.per_gt_iou[1] == 1.0 and scores.per_gt_iou[3] == 1.0
    assert scores.true_positives == 3
    assert scores.precision == pytest.approx(3 / 4)  # the other half (id 2) is a false positive
    assert scores.recall == 1.0


def test_split_below_threshold_is_not_a_true_positive():
    gt = [np.array([[1, 1, 1, 1]])]
    pred = [np.array([[4, 4, 5, 5]])]
    scores = match_instances(gt, pred)
    assert scores.per_gt_iou[1] == pytest.approx(0.5)
    assert scores.true_positives == 1  # IoU exactly 0.5 counts (>=)
    scores = match_instances(gt, [np.array([[4, 5, 5, 6]])])
    assert scores.per_gt_iou[1] == pytest.approx(0.5)
    gt3 = [np.array([[1, 1, 1]])]
    scores = match_instances(gt3, [np.array([[4, 5, 6]])])
    assert scores.per_gt_iou[1] == pytest.approx(1 / 3)
    assert scores.true_positives == 0 and scores.precision == 0.0 and scores.recall == 0.0


@pytest.mark.parametrize("none_value", [0, -1])
def test_empty_prediction(none_value):
    gt = _two_views()
    pred = [np.full(g.shape, none_value, dtype=np.int32) for g in gt]
    scores = match_instances(gt, pred)
    assert scores.miou == 0.0
    assert scores.precision == 0.0 and scores.recall == 0.0 and scores.f1 == 0.0
    assert all(m is None for m in scores.matches.values())
    assert len(scores.pred_ids) == 0


def test_iou_is_joint_over_views():
    """An id that follows the object in one view but not the other is scored on the pixel sum."""
    gt = [np.array([[1, 1, 0, 0]]), np.array([[0, 0, 1, 1]])]
    consistent = [np.array([[3, 3, 0, 0]]), np.array([[0, 0, 3, 3]])]
    assert match_instances(gt, consistent).miou == 1.0
    inconsistent = [np.array([[3, 3, 0, 0]]), np.array([[0, 0, 4, 4]])]
    scores = match_instances(gt, inconsistent)
    assert scores.per_gt_iou[1] == pytest.approx(0.5)
    table = contingency(gt, inconsistent)
    assert table.intersection.tolist() == [[2, 2]]
    assert table.gt_area.tolist() == [4] and table.pred_area.tolist() == [2, 2]


def test_hungarian_beats_greedy():
    # greedy on the largest IoU would give pred 5 to GT 1 (0.5) and leave GT 2 with nothing
    gt = [np.array([[1, 1, 1, 1, 2, 2]])]
    pred = [np.array([[5, 5, 5, 6, 5, 5]])]
    scores = match_instances(gt, pred)
    iou = {
        (int(g), int(p)): scores.iou[i, j] for i, g in enumerate(scores.gt_ids) for j, p in enumerate(scores.pred_ids)
    }
    assert iou[(1, 5)] == pytest.approx(3 / 6) and iou[(2, 5)] == pytest.approx(2 / 5)
    assert iou[(1, 6)] == pytest.approx(1 / 4) and iou[(2, 6)] == 0.0
    assert scores.matches == {1: 6, 2: 5}
    assert scores.miou == pytest.approx((1 / 4 + 2 / 5) / 2)


def test_accepts_stacked_arrays_and_single_views():
    gt = np.stack(_two_views())
    assert match_instances(gt, gt.astype(np.int16)).miou == 1.0
    assert match_instances(gt[0], gt[0]).miou == 1.0


@pytest.mark.parametrize(
    "gt, pred, message",
    [
        ([np.zeros((2, 2), int)], [np.zeros((2, 3), int)], "resize"),
        ([np.ones((2, 2), int)], [np.ones((2, 2), int)] * 2, "one prediction per GT view"),
        ([np.ones((2, 2), int)], [np.ones((2, 2), float)], "integer"),
        ([np.zeros((2, 2), int)], [np.ones((2, 2), int)], "no instance"),
        ([np.full((2, 2), -1)], [np.ones((2, 2), int)], "negative"),
        ([], [], "at least one"),
        ([np.ones((2, 2, 2), int)], [np.ones((2, 2, 2), int)], "2D"),
    ],
)
def test_bad_input_is_a_clear_error(gt, pred, message):
    with pytest.raises(ValueError, match=message):
        match_instances(gt, pred)


def test_bad_threshold():
    with pytest.raises(ValueError, match="iou_threshold"):
        match_instances([np.ones((2, 2), int)], [np.ones((2, 2), int)], iou_threshold=0.0)


def test_gaussian_purity_hand_case():
    gt = np.array([1, 1, 1, 1, 2, 2, 2, 0, 0, 3])
    pred = np.array([7, 7, 7, 8, 8, 8, 8, 8, -1, -1])
    s = gaussian_purity(pred, gt)
    # cluster 7 = {1,1,1} pure; cluster 8 = {1,2,2,2,0}: majority 2, purity 3/5
    assert s.per_cluster_purity == {7: 1.0, 8: pytest.approx(3 / 5)}
    assert s.cluster_majority == {7: 1, 8: 2}
    assert s.purity == pytest.approx((3 + 3) / 8)
    # instance 1: 3 of 4 in cluster 7; instance 2: 3 of 3; instance 3: unassigned
    assert s.per_gt_completeness == {1: pytest.approx(3 / 4), 2: 1.0, 3: 0.0}
    assert s.completeness == pytest.approx((3 + 3 + 0) / 8)
    assert s.assigned_fraction == pytest.approx(7 / 8)
    # 3D IoU: (1,7) = 3/4, (2,8) = 3/5, instance 3 unmatched
    assert s.miou_3d == pytest.approx((3 / 4 + 3 / 5 + 0.0) / 3)


def test_gaussian_purity_perfect_and_empty():
    gt = np.array([1, 1, 2, 2, 0])
    perfect = gaussian_purity(np.array([5, 5, 9, 9, 0]), gt)
    assert (perfect.purity, perfect.completeness, perfect.miou_3d, perfect.assigned_fraction) == (1.0, 1.0, 1.0, 1.0)
    empty = gaussian_purity(np.full(5, -1), gt)
    assert (empty.purity, empty.completeness, empty.miou_3d, empty.assigned_fraction) == (0.0, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="equal length"):
        gaussian_purity(np.zeros(3, int), np.zeros(4, int))
    with pytest.raises(ValueError, match="integers"):
        gaussian_purity(np.zeros(3), np.zeros(3, int))
    with pytest.raises(ValueError, match="empty"):
        gaussian_purity(np.zeros(0, int), np.zeros(0, int))
    with pytest.raises(ValueError, match="negative"):
        gaussian_purity(np.zeros(2, int), np.array([0, -1]))
    only_background = gaussian_purity(np.array([3, 3, 0]), np.zeros(3, int))
    assert only_background.purity == 1.0 and only_background.completeness == 0.0 and only_background.miou_3d == 0.0


def test_save_comparison_png(tmp_path):
    gt = _two_views()
    relabel = np.array([0, 7, 3, 12])
    pred = [relabel[g] for g in gt]
    pred[1][0, 7] = 40  # an extra, unmatched prediction
    out = save_comparison_png(gt, pred, tmp_path / "sub" / "cmp.png", scale=2, gap=4)
    picture = np.array(Image.open(out))
    h, w = gt[0].shape
    assert picture.shape == ((2 * h + 4) * 2, (2 * w + 4) * 2, 3)
    assert not list(out.parent.glob(".*"))  # no temp file left behind
    left = picture[: 2 * h, : 2 * w]
    right = picture[: 2 * h, (w + 4) * 2 : (2 * w + 4) * 2]
    assert np.array_equal(left, right)  # matched ids take their GT colour
    palette = instance_palette(4)
    assert tuple(left[2 * 1, 2 * 1]) == tuple(palette[1])
    assert tuple(left[0, 0]) == (0, 0, 0)
    row1 = picture[(h + 4) * 2 : (2 * h + 4) * 2]
    extra = row1[0, (w + 4) * 2 + 2 * 7]
    assert tuple(extra) not in {tuple(c) for c in palette} | {(255, 255, 255)}


# ----------------------------------------------------------------------------- reconstruction check


def test_psnr_and_flat_image_psnr_on_hand_images():
    target = np.zeros((4, 6, 3))
    target[:, :3] = 1.0  # half black, half white
    assert psnr(target + 0.1, target) == pytest.approx(20.0)  # MSE 0.01
    assert psnr(target, target) == float("inf")
    assert psnr(target * 255 + 25.5, target * 255, data_range=255) == pytest.approx(20.0)
    # the best constant image is the mean colour 0.5: MSE 0.25 -> 10 log10(4) dB
    assert flat_image_psnr(target) == pytest.approx(10 * np.log10(4))
    for grey in (0.3, 0.45, 0.55, 0.8):
        assert psnr(np.full_like(target, grey), target) < flat_image_psnr(target)
    # per channel: a red/green image's best constant is its mean colour, not one grey
    colour = np.zeros((2, 2, 3))
    colour[0, :, 0] = 1.0
    colour[1, :, 1] = 1.0
    assert flat_image_psnr(colour) == pytest.approx(psnr(np.broadcast_to([0.5, 0.5, 0.0], colour.shape), colour))
    with pytest.raises(ValueError, match="render at the image's size"):
        psnr(np.zeros((4, 6, 3)), np.zeros((4, 5, 3)))


def test_reconstruction_check_flags_a_view_far_below_the_median_or_no_better_than_a_flat_image():
    flat = [14.0, 14.0, 15.0, 13.0, 14.0, 14.0]
    check = check_reconstruction([30.0, 29.0, 31.0, 18.0, 30.5, 24.25], flat)
    assert check.median_psnr == pytest.approx(29.5)
    # 18 dB is 11.5 dB below the median; 24.25 is 5.25 below: kept
    assert check.ok.tolist() == [True, True, True, False, True, True]
    assert check.num_valid == 5
    # a threshold is inclusive: exactly 6 dB below the median, or exactly 2 dB above the flat image, passes
    assert check_reconstruction([30.0, 30.0, 24.0], [10.0, 10.0, 10.0]).ok.all()
    assert check_reconstruction([20.0, 20.0, 16.0], [10.0, 10.0, 14.0]).ok.all()
    assert check_reconstruction([20.0, 20.0, 15.99], [10.0, 10.0, 14.0]).ok.tolist() == [True, True, False]
    assert check_reconstruction([20.0, 20.0, 15.99], [10.0, 10.0, 14.0], min_gain_db=1.0).ok.all()

    # every view a grey wall: the median rule sees nothing wrong, the flat-image rule flags them all
    walls = check_reconstruction([13.0, 12.5, 13.9], [14.0, 13.0, 12.0])
    assert walls.ok.tolist() == [False, False, False]
    assert check_reconstruction([13.0, 12.5, 13.9], [14.0, 13.0, 12.0], min_gain_db=float("-inf")).ok.all()
    assert check_reconstruction([30.0, 29.0, 18.0], [14.0] * 3, max_psnr_drop_db=float("inf")).ok.all()

    # a NaN render is flagged and does not move the median; a perfect (infinite PSNR) one passes
    odd = check_reconstruction([float("nan"), 30.0, 28.0, float("inf")], [14.0] * 4)
    assert odd.ok.tolist() == [False, True, True, True]
    assert odd.median_psnr == 30.0
    summary = odd.to_dict()
    assert summary["num_views"] == 4 and summary["num_valid_views"] == 3 and summary["max_psnr_drop_db"] == 6.0
    entries = odd.per_view(["a", "b", "c", "d"])
    assert entries[1] == {"name": "b", "psnr": 30.0, "flat_psnr": 14.0, "reconstruction_ok": True}
    assert entries[0]["psnr"] is None and entries[3]["psnr"] is None  # JSON has no NaN / inf
    with pytest.raises(ValueError, match="3 view names for 4"):
        odd.per_view(["a", "b", "c"])

    for bad in (dict(max_psnr_drop_db=0.0), dict(max_psnr_drop_db=float("nan")), dict(min_gain_db=float("inf"))):
        with pytest.raises(ValueError):
            check_reconstruction([30.0], [14.0], **bad)
    with pytest.raises(ValueError, match="one PSNR and one flat-image PSNR per view"):
        check_reconstruction([30.0, 20.0], [14.0])


def test_reconstruction_check_is_scale_free():
    """Scaling the renders and images of every view by one factor (darker capture) changes no verdict."""
    rng = np.random.default_rng(0)
    targets = [rng.uniform(0.2, 0.8, size=(16, 16, 3)) for _ in range(5)]
    renders = [t + rng.normal(0, 0.03, size=t.shape) for t in targets]
    renders[2] = np.full_like(targets[2], 0.5) + rng.normal(0, 0.02, size=targets[2].shape)  # a grey wall
    renders[4] = targets[4] + rng.normal(0, 0.05, size=targets[4].shape)  # ~4.4 dB worse, still valid

    def verdict(factor):
        return check_reconstruction(
            [psnr(r * factor, t * factor) for r, t in zip(renders, targets)],
            [flat_image_psnr(t * factor) for t in targets],
        )

    base = verdict(1.0)
    assert base.ok.tolist() == [True, True, False, True, True]
    for factor in (0.25, 0.5):
        scaled = verdict(factor)
        assert scaled.ok.tolist() == base.ok.tolist()
        # every PSNR moves by the same -20 log10(factor) dB (errors shrink with the contrast)
        np.testing.assert_allclose(scaled.psnr - base.psnr, -20 * np.log10(factor), atol=1e-9)
        np.testing.assert_allclose(scaled.flat_psnr - base.flat_psnr, -20 * np.log10(factor), atol=1e-9)


# ----------------------------------------------------------------------------- what a user sees


def _objects_with_a_fragment():
    """20 Gaussians: object 1 (10), object 2 (4), background (6); instance 7 is a fragment of object 1."""
    gt = np.array([1] * 10 + [2] * 4 + [0] * 6)
    pred = np.array([5] * 8 + [7] * 2 + [9] * 4 + [5] * 2 + [9] * 4)
    return pred, gt


def test_per_object_completeness_and_purity():
    pred, gt = _objects_with_a_fragment()
    scores = gaussian_purity(pred, gt)
    assert scores.per_gt_completeness == {1: pytest.approx(0.8), 2: 1.0}
    assert scores.per_gt_match == {1: 5, 2: 9}
    # instance 5: 8 of object 1 + 2 background; instance 9: the 4 of object 2 + 4 background
    assert scores.per_gt_purity == {1: pytest.approx(0.8), 2: pytest.approx(0.5)}
    assert scores.per_gt_iou == {1: pytest.approx(8 / 12), 2: pytest.approx(0.5)}
    assert scores.mean_completeness == pytest.approx(0.9)
    assert scores.completeness == pytest.approx(12 / 14)  # the pooled one weights by size
    assert scores.mean_purity == pytest.approx(0.65)
    nothing = gaussian_purity(np.full(20, -1), gt)
    assert nothing.per_gt_purity == {1: None, 2: None} and nothing.mean_purity is None
    assert nothing.per_gt_match == {1: None, 2: None}


def test_a_fragment_lowers_list_precision():
    pred, gt = _objects_with_a_fragment()
    confidence = {5: 0.9, 7: 0.5, 9: 0.8}
    with_fragment = object_scores(pred, gt, confidence)
    assert with_fragment.num_predicted == 3 and with_fragment.num_gt == 2 and with_fragment.num_matched == 2
    assert with_fragment.matches == {1: 5, 2: 9}  # IoU 8/12 and exactly 0.5 (>=)
    assert with_fragment.list_precision == pytest.approx(2 / 3)
    whole = object_scores(np.where(pred == 7, -1, pred), gt, confidence)
    assert whole.list_precision == 1.0 and whole.num_predicted == 2
    # an object split 6/4: the larger piece is matched (IoU 0.6), the 4-piece (IoU 0.4) is not
    split = object_scores(np.array([3] * 6 + [4] * 4), np.ones(10, dtype=np.int64), {3: 1.0, 4: 1.0})
    assert split.matches == {1: 3} and split.list_precision == 0.5
    # half an object is no match at a threshold above 0.5
    assert object_scores(np.array([3] * 5 + [4] * 5), np.ones(10, dtype=np.int64), {3: 1, 4: 1}, 0.6).num_matched == 0
    empty = object_scores(np.full(10, -1), np.ones(10, dtype=np.int64), {})
    assert empty.list_precision == 0.0 and empty.num_predicted == 0 and empty.ap == 0.0


def _ap_case():
    """Three objects of 10 Gaussians; instances: 1 = object 1, 2 = 3 of object 2, 3 = its other 7, 4 = 4 of object 3."""
    gt = np.repeat([1, 2, 3], 10)
    pred = np.array([1] * 10 + [2] * 3 + [3] * 7 + [4] * 4 + [-1] * 6)
    return pred, gt


def test_ap_by_hand():
    pred, gt = _ap_case()
    # ranked 1, 2, 3, 4: TP, FP (IoU 0.3), TP (0.7), FP (0.4); precision 1, 1/2, 2/3, 1/2 at recall 1/3, 1/3, 2/3, 2/3
    result = average_precision_3d(pred, gt, {1: 0.9, 2: 0.8, 3: 0.7, 4: 0.6})
    assert result["order"] == [1, 2, 3, 4]
    assert result["precision"] == pytest.approx([1, 1 / 2, 2 / 3, 1 / 2])
    assert result["recall"] == pytest.approx([1 / 3, 1 / 3, 2 / 3, 2 / 3])
    # monotone envelope 1, 2/3, 2/3, 1/2; area = 1/3 * 1 + 1/3 * 2/3
    assert result["ap"] == pytest.approx(1 / 3 + 2 / 9)
    # the fragment ranked last: TP, TP, FP, FP -> 1/3 + 1/3
    assert average_precision_3d(pred, gt, {1: 0.9, 2: 0.1, 3: 0.7, 4: 0.6})["ap"] == pytest.approx(2 / 3)
    # a duplicate of an object already taken is a false positive even at IoU 1
    dup_pred = np.concatenate([pred, [5] * 10])
    dup_gt = np.concatenate([gt, [1] * 10])  # instance 5 = 10 more Gaussians of object 1
    ranked = average_precision_3d(dup_pred, dup_gt, {1: 0.1, 2: 0.8, 3: 0.7, 4: 0.6, 5: 0.9})
    assert ranked["order"] == [5, 2, 3, 4, 1]
    assert ranked["precision"] == pytest.approx([1, 1 / 2, 2 / 3, 1 / 2, 2 / 5])  # 1 (IoU 0.5) comes too late
    with pytest.raises(ValueError, match="no confidence"):
        average_precision_3d(pred, gt, {1: 0.9})


def test_score_level_reports_the_object_scores_and_ranks_by_size_without_a_confidence():
    pred, gt = _ap_case()
    view = np.zeros((2, 3), dtype=np.int64)
    view[0] = [1, 2, 3]
    pred_view = np.array([[0, 2, 3], [-1, -1, -1]])  # clustering ids: 0..3, -1 = none
    result = score_level([view], [pred_view], gt, pred - (pred > 0), iou_threshold=0.5)
    assert result["num_predicted"] == 4 and result["num_gt_objects"] == 3
    assert result["list_precision"] == pytest.approx(2 / 4)
    # sizes 10, 3, 7, 4: ranked 1, 3, 4, 2 -> TP, TP, FP, FP
    assert result["confidence_source"] == "size" and result["ap50_3d"] == pytest.approx(2 / 3)
    by_instance = {entry["id"]: entry for entry in result["per_instance"]}
    assert by_instance[2]["matched_instance_3d"] == 2 and by_instance[2]["matched_at_threshold_3d"] == 2
    assert by_instance[3]["completeness_3d"] == pytest.approx(0.4) and by_instance[3]["purity_3d"] == 1.0
    assert result["mean_completeness_3d"] == pytest.approx((1 + 0.7 + 0.4) / 3)
    given = score_level([view], [pred_view], gt, pred - (pred > 0), confidence=[0.9, 0.8, 0.7, 0.6])
    assert given["confidence_source"] == "instances" and given["ap50_3d"] == pytest.approx(1 / 3 + 2 / 9)


# the removal scene: a camera at the origin looking down +z at a square object (z = 2) before a wall (z = 4)
SIZE, FOCAL = 24, 24.0


def _grid(half: float, z: float, step: float):
    ticks = np.arange(-half + step / 2, half, step)
    x, y = np.meshgrid(ticks, ticks, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)


def _removal_scene():
    obj = _grid(0.5, 2.0, 0.1)  # projects to pixels 6..18
    wall = _grid(1.0, 4.0, 0.1)  # covers the whole view
    means = torch.tensor(np.concatenate([obj, wall]), dtype=torch.float32)
    n = means.shape[0]
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1)
    scales = torch.cat([torch.full((len(obj), 3), 0.06), torch.full((len(wall), 3), 0.12)])
    opacities = torch.full((n,), 0.99)
    labels = np.concatenate([np.ones(len(obj), np.int64), np.zeros(len(wall), np.int64)])
    K = torch.tensor([[FOCAL, 0, SIZE / 2], [0, FOCAL, SIZE / 2], [0, 0, 1.0]])
    view = PinholeView(torch.eye(4), K, SIZE, SIZE)
    gt_map = np.zeros((SIZE, SIZE), dtype=np.int64)
    gt_map[6:18, 6:18] = 1
    return (means, quats, scales, opacities), labels, view, gt_map, len(obj), obj


def test_ghost_fraction_ignores_the_opaque_background_behind_a_removed_object():
    gaussians, labels, view, gt_map, num_obj, obj = _removal_scene()
    everything = np.arange(num_obj)
    result = ghost_fractions(rasterize_torch, *gaussians, labels, {1: everything}, [view], [gt_map])[1]
    assert result["pixels"] == 144 and result["shown_before"] > 0.95
    assert result["ghost_fraction"] == 0.0
    # an opacity test would count every pixel: the wall behind is opaque where the object was
    keep = torch.ones(len(labels), dtype=torch.bool)
    keep[:num_obj] = False
    means, quats, scales, opacities = gaussians
    _, alpha, _ = rasterize_torch(
        means[keep],
        quats[keep],
        scales[keep],
        opacities[keep],
        torch.ones(int(keep.sum()), 1),
        torch.eye(4)[None],
        view.K[None],
        SIZE,
        SIZE,
    )
    assert (alpha[0, ..., 0].numpy()[gt_map == 1] > 0.5).all()
    # an instance that missed the object's left half leaves it behind as a ghost; the right half,
    # where the opaque wall now shows, is not one (an opacity test would give 100%)
    right = np.flatnonzero(obj[:, 0] > 0)
    half = ghost_fractions(rasterize_torch, *gaussians, labels, {1: right}, [view], [gt_map])[1]
    assert 0.4 < half["ghost_fraction"] < 0.7  # 72 of 144 pixels, plus the blur across the cut
    # no instance to remove: the ghost is everything the labelled Gaussians show
    none = ghost_fractions(rasterize_torch, *gaussians, labels, {1: None}, [view], [gt_map])[1]
    assert none["ghost_fraction"] == none["shown_before"]
    assert mean_ghost_percent({1: result, 2: half, 3: {"ghost_fraction": None}}) == pytest.approx(
        50 * half["ghost_fraction"]
    )


def test_ghost_leftovers_hidden_behind_another_surface_do_not_count():
    gaussians, labels, view, gt_map, num_obj, obj = _removal_scene()
    means, quats, scales, opacities = gaussians
    # the object's leftovers (its left half) sit behind a screen of background Gaussians at z = 1
    screen = torch.tensor(_grid(0.3, 1.0, 0.05), dtype=torch.float32)
    means = torch.cat([means, screen])
    quats = torch.cat([quats, torch.tensor([[1.0, 0, 0, 0]]).repeat(len(screen), 1)])
    scales = torch.cat([scales, torch.full((len(screen), 3), 0.04)])
    opacities = torch.cat([opacities, torch.full((len(screen),), 0.99)])
    labels = np.concatenate([labels, np.zeros(len(screen), np.int64)])
    right = np.flatnonzero(obj[:, 0] > 0)
    open_half = ghost_fractions(
        rasterize_torch, *_removal_scene()[0], _removal_scene()[1], {1: right}, [view], [gt_map]
    )
    hidden = ghost_fractions(rasterize_torch, means, quats, scales, opacities, labels, {1: right}, [view], [gt_map])
    assert hidden[1]["ghost_fraction"] < open_half[1]["ghost_fraction"] - 0.1
