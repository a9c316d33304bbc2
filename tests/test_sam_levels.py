"""SamLevelsMaskGenerator (all levels in one pass) gives segment_anything's labels, level by level.

The oracle is segment_anything's own SamAutomaticMaskGenerator, configured the same and run once
per level (tests/sam_reference.py). Driven by random-init SAM models and by a stand-in decoder over
label maps (tests/sam_stand_in.py) with which dozens of masks per level survive every filter.
"""

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from sam_reference import ReferenceGenerator
from sam_stand_in import StandInPredictor, scene
from test_mask_sources import blocks_image, tiny_sam

from votesplat_ns.core.sam_masks import SamLevelsMaskGenerator

LEVELS = ("default", "s", "m", "l")
LANGSPLAT = dict(
    points_per_side=12,
    points_per_batch=64,
    pred_iou_thresh=0.7,
    stability_score_thresh=0.85,
    box_nms_thresh=0.7,
    crop_n_layers=1,
    min_mask_region_area=100,
)
NO_MODEL = SimpleNamespace(image_encoder=SimpleNamespace(img_size=1024), mask_threshold=0.0)


def assert_same_labels(reference, fast):
    assert len(reference) == len(fast)
    for level, ref, out in zip(LEVELS, reference, fast):
        assert out.dtype == ref.dtype == np.int32 and out.shape == ref.shape
        assert np.array_equal(ref, out), f"level {level}: {int((ref != out).sum())} pixels differ"


@pytest.mark.parametrize("seed", [0, 1])
def test_stand_in_decoder_levels_equal_segment_anything(seed, one_torch_thread):
    image, maps = scene(96, 128, seed=seed, fine_cells=60)
    reference = ReferenceGenerator(NO_MODEL, StandInPredictor(image, maps, 1, seed=seed), LEVELS, **LANGSPLAT)
    expected = reference.label_images(image)
    fast = SamLevelsMaskGenerator(StandInPredictor(image, maps, 1, seed=seed), LEVELS, **LANGSPLAT)
    fast.stage_seconds = {}
    labels = fast.label_images(image)
    assert_same_labels(expected, labels)
    # the workload is not trivial: dozens of masks per image survive, some reshaped by the small-region removal
    counts = [len(np.unique(level)) - 1 for level in labels]
    assert counts[0] >= 40 and min(counts) >= 4, counts
    changed = [a for level in LEVELS[1:] for a in reference.annotations[level] if a["stability_score"] < 1]
    assert changed
    assert {"encoder", "decoder", "filter", "nms", "small_regions", "paint"} <= set(fast.stage_seconds)


def test_stand_in_without_crops_or_small_region_removal(one_torch_thread):
    image, maps = scene(80, 64, seed=3, fine_cells=30)
    options = {**LANGSPLAT, "crop_n_layers": 0, "min_mask_region_area": 0, "pred_iou_thresh": 0.6}
    expected = ReferenceGenerator(NO_MODEL, StandInPredictor(image, maps, 0), LEVELS, **options).label_images(image)
    labels = SamLevelsMaskGenerator(StandInPredictor(image, maps, 0), LEVELS, **options).label_images(image)
    assert_same_labels(expected, labels)
    assert all(level.max() > 0 for level in labels)  # random weights: few masks, but some at every level


def test_tiny_random_sam_with_crops_equals_segment_anything(one_torch_thread):
    from segment_anything import SamPredictor

    sam = tiny_sam()
    image = blocks_image()
    for options in (
        dict(
            points_per_side=4, pred_iou_thresh=0.0, stability_score_thresh=0.0, crop_n_layers=1, min_mask_region_area=20
        ),
        dict(
            points_per_side=5,
            pred_iou_thresh=0.0,
            stability_score_thresh=0.0,
            box_nms_thresh=0.9,
            crop_n_layers=1,
            min_mask_region_area=0,
        ),
        dict(points_per_side=3, pred_iou_thresh=2.0, stability_score_thresh=0.0, crop_n_layers=1),  # nothing kept
    ):
        expected = ReferenceGenerator(sam, None, LEVELS, **options).label_images(image)
        labels = SamLevelsMaskGenerator(SamPredictor(sam), LEVELS, **options).label_images(image)
        assert_same_labels(expected, labels)
        assert (labels[0].max() > 0) == (options["pred_iou_thresh"] < 1)


def test_sam_mask_source_runs_the_one_pass_generator(one_torch_thread):
    from votesplat_ns.core.mask_sources import SamMaskSource

    sam = tiny_sam()
    options = dict(points_per_side=4, pred_iou_thresh=0.0, stability_score_thresh=0.0, min_mask_region_area=20)
    source = SamMaskSource(sam_model=sam, device="cpu", levels=("m", "default", "s"), **options)
    image = blocks_image()
    labels = source.masks_for_image(image, "blocks.png", 0)
    assert isinstance(source._generator, SamLevelsMaskGenerator)
    settings = {**source.generator_kwargs}
    expected = ReferenceGenerator(sam, None, ("m", "default", "s"), **settings).label_images(image)
    assert all(np.array_equal(a, b) for a, b in zip(expected, labels))
    assert labels[1].max() > 0


def vit_b_predictor(sam):
    """A SamPredictor over random-init vit_b whose image features are a fixed random tensor of the encoder's output
    shape: both paths get the same features either way, and a vit_b encoder pass takes over a minute on a CI CPU
    (the encoder itself runs in the tiny-model test above). Prompt encoder and mask decoder are vit_b's."""
    from segment_anything import SamPredictor

    class FixedFeaturesPredictor(SamPredictor):
        def set_torch_image(self, transformed_image, original_image_size):
            self.reset_image()
            self.original_size = original_image_size
            self.input_size = tuple(transformed_image.shape[-2:])
            generator = torch.Generator().manual_seed(7)
            self.features = torch.randn(1, 256, 64, 64, generator=generator)
            self.is_image_set = True

    return FixedFeaturesPredictor(sam)


def test_random_vit_b_decoder_equals_segment_anything(one_torch_thread):
    from segment_anything import sam_model_registry

    torch.manual_seed(0)
    sam = sam_model_registry["vit_b"](checkpoint=None).eval()
    image = np.ascontiguousarray(np.kron(blocks_image(), np.ones((2, 2, 1), dtype=np.uint8)))  # 48 x 64
    options = dict(
        points_per_side=3,
        pred_iou_thresh=0.0,
        stability_score_thresh=0.0,
        box_nms_thresh=0.98,
        crop_n_layers=0,
        min_mask_region_area=30,
    )  # few points: each decoder call upsamples every mask to 1024 x 1024 on the CPU
    expected = ReferenceGenerator(sam, vit_b_predictor(sam), LEVELS, **options).label_images(image)
    labels = SamLevelsMaskGenerator(vit_b_predictor(sam), LEVELS, **options).label_images(image)
    assert_same_labels(expected, labels)
    assert all(level.max() > 0 for level in labels)  # random weights: few masks, but some at every level


def random_blob_mask(rng, shape):
    """A mask of a few random blobs, specks and holes, sometimes touching the image's borders."""
    import cv2

    height, width = shape
    mask = np.zeros(shape, dtype=np.uint8)
    for _ in range(rng.integers(1, 4)):
        centre = (int(rng.integers(-5, width + 5)), int(rng.integers(-5, height + 5)))
        axes = (int(rng.integers(1, width // 2)), int(rng.integers(1, height // 2)))
        cv2.ellipse(mask, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
    speckle = rng.random(shape) < rng.choice([0.0, 0.01, 0.03])
    return (mask.astype(bool) ^ speckle) & (rng.random() > 0.02)


def test_windowed_small_region_removal_equals_segment_anything_on_the_whole_image():
    from votesplat_ns.core.sam_masks import _small_regions_removed, _small_regions_removed_whole_image, _Window

    rng = np.random.default_rng(0)
    for trial in range(300):
        shape = (int(rng.integers(8, 60)), int(rng.integers(8, 60)))
        mask = random_blob_mask(rng, shape)
        min_area = int(rng.choice([3, 10, 30, 100]))
        window = _Window.of(mask)
        expected, expected_unchanged = _small_regions_removed_whole_image(window, shape, min_area)
        result, unchanged = _small_regions_removed(window, shape, min_area)
        assert np.array_equal(result.full(shape), expected.full(shape)), trial
        assert unchanged == expected_unchanged, trial
