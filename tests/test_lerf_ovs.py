"""LERF-OVS labels: parsing, rasterisation, the 3D-selection metrics and the writer (votesplat_ns.eval.lerf_ovs)."""

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from test_semantics import ColourHistogramEncoder

from votesplat_ns.core.semantics import instance_features, query_text, select_instances
from votesplat_ns.eval.lerf_ovs import (
    LabelFrame,
    LabelWarning,
    category_masks,
    evaluate_scene,
    frame_from_masks,
    frame_image_index,
    load_label_frame,
    load_scene_labels,
    mask_iou,
    mask_to_polygons,
    parse_label_frame,
    polygon_area,
    polygon_perimeter,
    rasterise_polygon,
    silhouette_mask,
    summarise_scenes,
    write_label_frame,
)

LOCAL_LABELS = Path(__file__).resolve().parent / "data" / "lerf_ovs"
SHARED_LABELS = Path(__file__).resolve().parents[2] / "shared" / "data" / "lerf_ovs_labels"


def _local_frames():
    return load_scene_labels(LOCAL_LABELS / "waldo_kitchen")


def _assert_masks_match_area_fields(frame: LabelFrame):
    """Each polygon's mask against its ``area`` field (the shoelace area of the vertex polygon).

    The polygon runs through the centres of the boundary pixels and the outline is in the mask, so
    the mask has the area plus about half a pixel per unit of outline (Pick's theorem; cv2's
    8-connected slanted edges take a little more): between a quarter and one pixel per unit of
    outline above the area. A rasteriser that drops the outline falls below the lower bound.
    """
    for obj in frame.objects:
        assert obj.area == pytest.approx(polygon_area(obj.polygon), abs=0.5)
        count = int(rasterise_polygon(obj.polygon, frame.width, frame.height).sum())
        perimeter = polygon_perimeter(obj.polygon)
        assert obj.area + perimeter / 4 <= count <= obj.area + perimeter, (
            frame.name,
            obj.category,
            count,
            obj.area,
            perimeter,
        )


def _langsplat_masks(label_path: Path):
    """LangSplat's GT masks of one label file, rebuilt from the raw JSON as its eval/utils.py does.

    Per object ``polygon_to_mask``: ``cv2.fillPoly(zeros, [np.asarray(points, dtype=np.int32)], 1)``;
    objects of one category are merged (``stack_mask``). Returns ([(category, object mask)], {category: mask}).
    """
    import cv2

    raw = json.loads(label_path.read_text(encoding="utf-8"))
    height, width = raw["info"]["height"], raw["info"]["width"]
    objects, merged = [], {}
    for entry in raw["objects"]:
        mask = np.zeros((height, width), dtype=np.uint8)
        cv2.fillPoly(mask, [np.asarray(entry["segmentation"], dtype=np.int32)], 1)
        objects.append((entry["category"], mask.astype(bool)))
        merged[entry["category"]] = merged.get(entry["category"], np.zeros((height, width), bool)) | mask.astype(bool)
    return objects, merged


def _assert_pixel_exact_against_langsplat(label_paths):
    """Every object mask and every merged category mask equals LangSplat's; returns (objects, pixels) checked."""
    objects_checked = pixels = 0
    for path in label_paths:
        frame = load_label_frame(path)
        reference_objects, reference_merged = _langsplat_masks(path)
        assert [obj.category for obj in frame.objects] == [category for category, _ in reference_objects]
        for obj, (_, reference) in zip(frame.objects, reference_objects):
            ours = rasterise_polygon(obj.polygon, frame.width, frame.height)
            assert ours.shape == reference.shape and ours.dtype == bool
            assert np.array_equal(ours, reference), (path.name, obj.category, int((ours != reference).sum()))
            objects_checked += 1
            pixels += int(reference.sum())
        masks = category_masks(frame)
        assert list(masks) == list(reference_merged)
        assert all(np.array_equal(masks[c], reference_merged[c]) for c in masks), path.name
    return objects_checked, pixels


def test_rasterisation_convention_on_hand_polygons():
    rectangle = ((1, 1), (5, 1), (5, 3), (1, 3))
    mask = rasterise_polygon(rectangle, 8, 6)
    expected = np.zeros((6, 8), dtype=bool)
    expected[1:4, 1:6] = True  # vertices are pixel indices; outline pixels included
    assert np.array_equal(mask, expected)
    # Pick's theorem: lattice points inside or on = area + boundary_points/2 + 1 = 8 + 12/2 + 1.
    assert mask.sum() == polygon_area(rectangle) + 12 / 2 + 1
    # Fractional vertices are truncated, as LangSplat's int32 cast does.
    assert np.array_equal(rasterise_polygon(((1.9, 1.2), (5.99, 1.0), (5.5, 3.7), (1.0, 3.0)), 8, 6), expected)

    # A slanted edge: cv2 draws the hypotenuse (7, 1) -> (1, 4) as an 8-connected line, one pixel per
    # column at y = 1 + (7 - x) / 2 rounded half up (x=6 -> row 2, x=4 -> row 3, x=2 -> row 4), and
    # fills each row out to that line, so rows 2..4 end at x = 6, 4, 2 and the outline is included.
    triangle_mask = np.array(
        [
            [0, 0, 0, 0, 0, 0, 0, 0, 0],
            [0, 1, 1, 1, 1, 1, 1, 1, 0],
            [0, 1, 1, 1, 1, 1, 1, 0, 0],
            [0, 1, 1, 1, 1, 0, 0, 0, 0],
            [0, 1, 1, 0, 0, 0, 0, 0, 0],
            [0, 0, 0, 0, 0, 0, 0, 0, 0],
        ],
        dtype=bool,
    )
    assert np.array_equal(rasterise_polygon(((1, 1), (7, 1), (1, 4)), 9, 6), triangle_mask)
    # The same triangle with fractional vertices: truncated (rounding would move (7.5, 1) to column 8
    # and (1, 4.99) to row 5).
    assert np.array_equal(rasterise_polygon(((1.9, 1.2), (7.5, 1.0), (1.0, 4.99)), 9, 6), triangle_mask)

    diamond = ((3, 0), (6, 3), (3, 6), (0, 3))
    diamond_mask = rasterise_polygon(diamond, 7, 7)
    rows, cols = np.mgrid[0:7, 0:7]
    assert np.array_equal(diamond_mask, np.abs(rows - 3) + np.abs(cols - 3) <= 3)
    # Vertices outside the image are clipped, not an error.
    assert rasterise_polygon(((-5, -5), (20, -5), (20, 20), (-5, 20)), 4, 3).all()
    with pytest.raises(ValueError, match="non-finite"):
        rasterise_polygon(((0, 0), (float("nan"), 1), (2, 2)), 4, 4)
    with pytest.raises(ValueError, match="int32"):
        rasterise_polygon(((0, 0), (2.0**31, 1), (2, 2)), 4, 4)


def test_real_label_files_parse_and_masks_match_their_area_fields():
    frames = _local_frames()
    assert [frame.stem for frame in frames] == ["frame_00066", "frame_00089"]
    for frame in frames:
        raw = json.loads(Path(frame.source).read_text(encoding="utf-8"))
        assert (frame.width, frame.height) == (raw["info"]["width"], raw["info"]["height"])
        assert len(frame.objects) == len(raw["objects"])
        assert [obj.category for obj in frame.objects] == [o["category"] for o in raw["objects"]]
        for obj, raw_obj in zip(frame.objects, raw["objects"]):
            assert obj.vertices.tolist() == raw_obj["segmentation"]
            assert list(obj.bbox) == raw_obj["bbox"]
        _assert_masks_match_area_fields(frame)


def test_rasterisation_matches_langsplats_masks_pixel_for_pixel_on_the_local_labels():
    objects, pixels = _assert_pixel_exact_against_langsplat(
        sorted((LOCAL_LABELS / "waldo_kitchen").glob("frame_*.json"))
    )
    assert objects > 10 and pixels > 10_000


@pytest.mark.skipif(not SHARED_LABELS.is_dir(), reason=f"shared label set not checked out at {SHARED_LABELS}")
def test_rasterisation_matches_langsplats_masks_pixel_for_pixel_on_every_shared_polygon():
    paths = sorted(SHARED_LABELS.glob("*/frame_*.json"))
    assert len(paths) == 22
    objects, pixels = _assert_pixel_exact_against_langsplat(paths)
    assert objects == sum(len(json.loads(p.read_text(encoding="utf-8"))["objects"]) for p in paths)
    assert pixels > 1_000_000


@pytest.mark.skipif(not SHARED_LABELS.is_dir(), reason=f"shared label set not checked out at {SHARED_LABELS}")
def test_all_22_shared_frames_parse_with_the_object_counts_the_readme_lists():
    readme = (SHARED_LABELS / "README.md").read_text(encoding="utf-8")
    listed = {}
    for scene, sizes, frames_text in re.findall(r"^(\w+) \((\d+x\d+)\): (.+)$", readme, flags=re.M):
        for stem, count in re.findall(r"(frame_\d+) (\d+)", frames_text):
            listed[(scene, stem)] = (int(count), sizes)
    assert len(listed) == 22

    parsed = {}
    for scene_dir in sorted(path for path in SHARED_LABELS.iterdir() if path.is_dir()):
        for frame in load_scene_labels(scene_dir):
            parsed[(scene_dir.name, frame.stem)] = (len(frame.objects), f"{frame.width}x{frame.height}")
            _assert_masks_match_area_fields(frame)
            masks = category_masks(frame)
            assert list(masks) == list(frame.categories)
    assert parsed == listed


def test_objects_of_one_category_merge_into_one_mask():
    frame = load_label_frame(LOCAL_LABELS / "waldo_kitchen" / "frame_00089.json")
    knives = [obj for obj in frame.objects if obj.category == "knife"]
    assert len(knives) > 1
    masks = category_masks(frame)
    union = np.zeros((frame.height, frame.width), dtype=bool)
    for obj in knives:
        union |= rasterise_polygon(obj.polygon, frame.width, frame.height)
    assert np.array_equal(masks["knife"], union)
    assert set(masks) == {obj.category for obj in frame.objects}
    assert all(mask.shape == (frame.height, frame.width) and mask.dtype == bool for mask in masks.values())


def test_frame_image_index_follows_langsplat_and_checks_range():
    frame = load_label_frame(LOCAL_LABELS / "waldo_kitchen" / "frame_00066.json")
    assert frame.frame_number == 66
    assert frame_image_index(frame, num_images=66) == 65
    for too_few in (65, 0):
        with pytest.raises(ValueError, match="outside the scene's"):
            frame_image_index(frame, num_images=too_few)


def _raw_frame(objects):
    return {"info": {"name": "frame_00007.jpg", "width": 10, "height": 8, "depth": 3, "note": ""}, "objects": objects}


def _raw_object(category, points):
    return {"category": category, "segmentation": [list(p) for p in points]}


def test_polygons_with_fewer_than_three_vertices_are_skipped_with_a_warning():
    raw = _raw_frame(
        [
            _raw_object("cup", [(1, 1), (4, 1), (4, 4)]),
            _raw_object("cup", [(6, 6), (7, 7)]),
            _raw_object("spoon", []),
        ]
    )
    with pytest.warns(LabelWarning) as caught:
        frame = parse_label_frame(raw, source="hand.json")
    assert len(caught) == 2 and "hand.json" in str(caught[0].message)
    assert [obj.category for obj in frame.objects] == ["cup"]
    assert frame.objects[0].area == polygon_area(((1, 1), (4, 1), (4, 4)))  # computed when absent
    assert frame.objects[0].bbox == (1.0, 1.0, 4.0, 4.0)

    outside = parse_label_frame(_raw_frame([_raw_object("far", [(20, 20), (30, 20), (30, 30)])]))
    with pytest.warns(LabelWarning, match="covers no pixel"):
        assert category_masks(outside) == {}


@pytest.mark.parametrize(
    "raw, message",
    [
        ({"objects": []}, "needs top-level 'info'"),
        ({"info": {"name": "f.jpg", "width": 0, "height": 3}, "objects": []}, "positive integer"),
        ({"info": {"name": "f.jpg", "width": 4}, "objects": []}, "no 'height'"),
        (_raw_frame([_raw_object("", [(0, 0), (1, 0), (1, 1)])]), "no category"),
        (_raw_frame([{"category": "cup", "segmentation": [[0, 0], [1], [1, 1]]}]), "not an \\[x, y\\] pair"),
        (_raw_frame([{"category": "cup", "segmentation": [[0, 0], [1, float("nan")], [1, 1]]}]), "finite"),
        (_raw_frame([{"category": "cup", "segmentation": [[0, 0], [1, 0], [1, 1]], "bbox": [0, 1]}]), "bbox"),
    ],
)
def test_malformed_labels_are_clear_errors(raw, message):
    with pytest.raises(ValueError, match=message):
        parse_label_frame(raw)


def test_missing_files_and_folders_are_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        load_label_frame(tmp_path / "frame_00001.json")
    with pytest.raises(ValueError, match="no frame_"):
        load_scene_labels(tmp_path)
    (tmp_path / "frame_00001.json").write_text("{not json", encoding="utf-8")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_label_frame(tmp_path / "frame_00001.json")


def test_mask_iou_and_silhouette_threshold_on_hand_cases():
    predicted = np.array([[1, 1], [0, 0]], dtype=bool)
    ground_truth = np.array([[1, 0], [1, 0]], dtype=bool)
    assert mask_iou(predicted, ground_truth) == pytest.approx(1 / 3)
    assert mask_iou(ground_truth, ground_truth) == 1.0
    assert mask_iou(~ground_truth, ground_truth) == 0.0
    assert mask_iou(np.zeros((2, 2), bool), np.zeros((2, 2), bool)) == 0.0  # empty union counts 0
    assert mask_iou(torch.tensor([[1, 1], [0, 0]]), ground_truth.astype(np.uint8)) == pytest.approx(1 / 3)
    with pytest.raises(ValueError, match="label resolution"):
        mask_iou(np.zeros((3, 2), bool), ground_truth)
    with pytest.raises(ValueError, match="silhouette_mask"):
        mask_iou(np.full((2, 2), 0.8), ground_truth)

    accumulation = np.array([[0.7, 0.71], [0.0, 1.0]])
    assert silhouette_mask(accumulation).tolist() == [[False, True], [False, True]]
    assert silhouette_mask(torch.tensor(accumulation)[..., None], threshold=0.5).tolist() == [
        [True, True],
        [False, True],
    ]
    with pytest.raises(ValueError, match="non-finite"):
        silhouette_mask(np.array([[np.nan]]))


def _square(shape, top, left, size):
    mask = np.zeros(shape, dtype=bool)
    mask[top : top + size, left : left + size] = True
    return mask


def test_scene_metrics_on_a_hand_scene():
    shape = (20, 30)
    frame_a = frame_from_masks("frame_00001.jpg", {"cup": _square(shape, 2, 2, 4), "plate": _square(shape, 10, 10, 4)})
    frame_b = frame_from_masks("frame_00002.jpg", {"cup": _square(shape, 0, 20, 6)})
    truth = {
        (frame.stem, category): mask for frame in (frame_a, frame_b) for category, mask in category_masks(frame).items()
    }

    def predict(frame, text):
        gt = truth[(frame.stem, text)]
        if (frame.stem, text) == ("frame_00001", "cup"):
            return gt  # IoU 1
        if (frame.stem, text) == ("frame_00001", "plate"):
            return _square(shape, 10, 10, 2)  # 4 of 16 pixels: IoU exactly 0.25, not counted by mAcc@0.25
        return None  # nothing selected: IoU 0

    score = evaluate_scene([frame_a, frame_b], predict, scene="hand")
    assert [(q.frame, q.category) for q in score.queries] == [
        ("frame_00001", "cup"),
        ("frame_00001", "plate"),
        ("frame_00002", "cup"),
    ]
    assert [q.iou for q in score.queries] == [1.0, 0.25, 0.0]
    assert score.miou == pytest.approx((1.0 + 0.25 + 0.0) / 3)
    assert score.accuracy(0.25) == pytest.approx(1 / 3)
    assert score.to_dict()["mAcc@0.5"] == pytest.approx(1 / 3)

    perfect = evaluate_scene([frame_a, frame_b], lambda frame, text: truth[(frame.stem, text)], scene="perfect")
    summary = summarise_scenes([score, perfect])
    assert summary["scenes"]["perfect"]["mIoU"] == 1.0
    assert summary["mean"]["mIoU"] == pytest.approx((score.miou + 1.0) / 2)
    assert summary["mean"]["mAcc@0.25"] == pytest.approx((1 / 3 + 1.0) / 2)
    with pytest.raises(ValueError, match="distinct"):
        summarise_scenes([score, score])
    with pytest.raises(ValueError, match="no scene scores"):
        summarise_scenes([])


def test_queries_mapping_renames_known_categories_and_rejects_unknown_ones():
    shape = (12, 12)
    frame = frame_from_masks("frame_00003.jpg", {"ottolenghi": _square(shape, 1, 1, 5)})
    asked = []

    def predict(frame, text):
        asked.append(text)
        return category_masks(frame)["ottolenghi"]

    score = evaluate_scene([frame], predict, queries={"ottolenghi": "cookbook"})
    assert asked == ["cookbook"] and score.miou == 1.0
    with pytest.raises(ValueError, match=r"not in the labels.*'ottolenghi'"):
        evaluate_scene([frame], predict, queries={"cook book": "cookbook"})
    with pytest.raises(ValueError, match="no label frames"):
        evaluate_scene([], predict)
    with pytest.raises(ValueError, match="label resolution"):
        evaluate_scene([frame], lambda frame, text: np.zeros((5, 5), bool))
    with pytest.raises(ValueError, match="bool"):
        evaluate_scene([frame], lambda frame, text: np.full(shape, 0.9))


def test_writer_round_trips_real_label_files(tmp_path):
    for frame in _local_frames():
        path = tmp_path / "waldo_kitchen" / f"{frame.stem}.json"
        write_label_frame(path, frame)
        again = load_label_frame(path)
        assert again == frame  # every field but the source path
        original_masks, written_masks = category_masks(frame), category_masks(again)
        assert list(original_masks) == list(written_masks)
        assert all(np.array_equal(original_masks[c], written_masks[c]) for c in original_masks)
    assert sorted(p.name for p in (tmp_path / "waldo_kitchen").iterdir()) == ["frame_00066.json", "frame_00089.json"]


def test_masks_written_as_labels_come_back_unchanged(tmp_path):
    rng = np.random.default_rng(3)
    shape = (24, 32)
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    disc = (rows - 8) ** 2 + (cols - 9) ** 2 <= 30
    ring_with_hole = ((rows - 15) ** 2 + (cols - 24) ** 2 <= 40) & ((rows - 15) ** 2 + (cols - 24) ** 2 > 6)
    speckles = rng.random(shape) < 0.04  # many one- and two-pixel components
    two_pieces = _square(shape, 18, 2, 3) | _square(shape, 18, 8, 2)
    masks = {
        "disc": disc,
        "ring": ring_with_hole,
        "speckles": speckles & ~disc & ~ring_with_hole,
        "pieces": [two_pieces, _square(shape, 0, 28, 3)],
        "hidden": np.zeros(shape, bool),
    }

    frame = frame_from_masks("frame_00012.jpg", masks)
    write_label_frame(tmp_path / "frame_00012.json", frame)
    loaded = load_scene_labels(tmp_path)[0]
    assert loaded.frame_number == 12 and (loaded.width, loaded.height) == (32, 24)
    got = category_masks(loaded)
    assert "hidden" not in got  # not visible in this frame, so not annotated
    assert np.array_equal(got["disc"], disc)
    assert np.array_equal(got["speckles"], masks["speckles"])
    assert np.array_equal(got["pieces"], two_pieces | _square(shape, 0, 28, 3))
    hole = (rows - 15) ** 2 + (cols - 24) ** 2 <= 6
    assert np.array_equal(got["ring"], ring_with_hole | hole)  # the format has no holes: they are filled
    assert sum(obj.category == "pieces" for obj in loaded.objects) == 3  # one object per component

    assert len(mask_to_polygons(np.zeros(shape, bool))) == 0
    with pytest.raises(ValueError, match="share the image size"):
        frame_from_masks("frame_00001.jpg", {"a": disc, "b": disc[:10]})
    with pytest.raises(ValueError, match="no masks"):
        frame_from_masks("frame_00001.jpg", {})


def test_synthetic_scene_scored_end_to_end_with_text_selection(tmp_path):
    """Named objects -> label files -> text query over instance features -> selection masks -> metrics."""
    shape = (30, 40)
    colours = {0: (230, 20, 20), 1: (20, 210, 30), 2: (20, 30, 220)}
    names = {0: "red mug", 1: "green apple", 2: "blue bowl"}
    instance_maps, images = [], []
    for view, shift in enumerate((0, 3)):
        instance_map = np.full(shape, -1, dtype=np.int64)
        instance_map[2 + shift : 12 + shift, 3:15] = 0
        instance_map[15:27, 5 + shift : 20 + shift] = 1
        instance_map[4:24, 25 : 36 - shift] = 2
        image = np.full(shape + (3,), 100, dtype=np.uint8)
        for instance, colour in colours.items():
            image[instance_map == instance] = colour
        instance_maps.append(instance_map)
        images.append(image)
        masks = {names[i]: instance_map == i for i in names}
        write_label_frame(
            tmp_path / "synthetic" / f"frame_{view + 1:05d}.json", frame_from_masks(f"frame_{view + 1:05d}.jpg", masks)
        )

    encoder = ColourHistogramEncoder()
    features = instance_features(images, instance_maps, encoder, min_pixels=16)
    frames = load_scene_labels(tmp_path / "synthetic")

    def predict(frame, text):
        selected = select_instances(query_text(text, features, encoder))
        return np.isin(instance_maps[frame_image_index(frame, len(images))], selected)

    score = evaluate_scene(frames, predict, scene="synthetic")
    assert len(score.queries) == 6
    assert score.miou == 1.0 and score.accuracy(0.25) == 1.0

    def predict_wrong(frame, text):
        ranked = query_text(text, features, encoder)
        return instance_maps[frame_image_index(frame, len(images))] == ranked[-1][0]

    assert evaluate_scene(frames, predict_wrong, scene="wrong").miou == 0.0
