"""SamLevelsMaskGenerator (all levels in one pass) gives segment_anything's labels, level by level.

The oracle is segment_anything's own SamAutomaticMaskGenerator, configured the same and run once
per level (tests/sam_reference.py). Driven by random-init SAM models and by a stand-in decoder over
label maps (tests/sam_stand_in.py) with which dozens of masks per level survive every filter.
"""

import functools
import re
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from sam_reference import ReferenceGenerator
from sam_stand_in import StandInPredictor, scene
from segment_anything import SamPredictor
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
    assert {"encoder", "decoder", "filter", "nms", "masks", "small_regions", "paint"} <= set(fast.stage_seconds)


def test_stand_in_without_crops_or_small_region_removal(one_torch_thread):
    image, maps = scene(80, 64, seed=3, fine_cells=30)
    options = {**LANGSPLAT, "crop_n_layers": 0, "min_mask_region_area": 0, "pred_iou_thresh": 0.6}
    expected = ReferenceGenerator(NO_MODEL, StandInPredictor(image, maps, 0), LEVELS, **options).label_images(image)
    labels = SamLevelsMaskGenerator(StandInPredictor(image, maps, 0), LEVELS, **options).label_images(image)
    assert_same_labels(expected, labels)
    assert all(level.max() > 0 for level in labels)  # random weights: few masks, but some at every level


def test_tiny_random_sam_with_crops_equals_segment_anything(one_torch_thread):
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
        dict(  # several decoder batches per crop, the last one short
            points_per_side=5,
            points_per_batch=7,
            pred_iou_thresh=0.0,
            stability_score_thresh=0.0,
            crop_n_layers=1,
            min_mask_region_area=20,
        ),
    ):
        expected = ReferenceGenerator(sam, None, LEVELS, **options).label_images(image)
        labels = SamLevelsMaskGenerator(SamPredictor(sam), LEVELS, **options).label_images(image)
        assert_same_labels(expected, labels)
        assert (labels[0].max() > 0) == (options["pred_iou_thresh"] < 1)


def test_masks_upscaled_one_at_a_time_and_with_the_model_alongside_are_the_same(one_torch_thread):
    """A mask upscaled alone has the bits it has in a batch; the stand-in gives the same masks with a model running
    alongside (its timing mode), whose low-resolution logits then carry the stand-in's segments."""
    image, maps = scene(64, 96, seed=4, fine_cells=40)
    expected = ReferenceGenerator(NO_MODEL, StandInPredictor(image, maps, 1, seed=4), LEVELS, **LANGSPLAT).label_images(
        image
    )
    one_at_a_time = SamLevelsMaskGenerator(
        StandInPredictor(image, maps, 1, seed=4), LEVELS, upscale_budget_bytes=1, **LANGSPLAT
    )
    assert one_at_a_time._chunk((64, 96)) == 1
    assert_same_labels(expected, one_at_a_time.label_images(image))
    with_model = StandInPredictor(image, maps, 1, seed=4, model_predictor=SamPredictor(tiny_sam()))
    assert_same_labels(expected, SamLevelsMaskGenerator(with_model, LEVELS, **LANGSPLAT).label_images(image))
    reference_with_model = StandInPredictor(image, maps, 1, seed=4, model_predictor=SamPredictor(tiny_sam()))
    assert_same_labels(
        expected, ReferenceGenerator(NO_MODEL, reference_with_model, LEVELS, **LANGSPLAT).label_images(image)
    )


def test_crops_encoded_in_one_call_get_the_features_of_one_call_each(one_torch_thread):
    from votesplat_ns.core.sam_masks import SamSteps

    sam = tiny_sam()
    image = blocks_image()
    crops = [image, image[:16, :20], image[8:, 12:], image[:, ::-1].copy()]
    alone = SamSteps(SamPredictor(sam)).encode_crops(crops)
    together = SamSteps(SamPredictor(sam), crops_per_encoder_pass=3).encode_crops(crops)
    for one, batched in zip(alone, together):
        assert one.original_size == batched.original_size and one.input_size == batched.input_size
        assert batched.features.shape == one.features.shape == (1, 32, 4, 4)
        torch.testing.assert_close(batched.features, one.features, rtol=1e-5, atol=1e-6)


def test_sam_precisions(one_torch_thread):
    """tf32 is fp32 on a CPU (and leaves torch's matmul precision as it was); bf16 runs SAM under autocast: other
    logits, masks close to fp32's, and a cache key of its own."""
    from votesplat_ns.core.sam_masks import SamMaskSource, SamSteps
    from votesplat_ns.errors import VoteSplatInputError

    sam = tiny_sam()
    image = blocks_image()
    options = dict(points_per_side=4, pred_iou_thresh=0.0, stability_score_thresh=0.0, min_mask_region_area=20)
    labels, keys = {}, {}
    for precision in ("fp32", "tf32", "bf16"):
        source = SamMaskSource(sam_model=sam, device="cpu", precision=precision, **options)
        labels[precision] = source.masks_for_image(image, "blocks.png", 0)
        keys[precision] = source.config_key()
        assert torch.get_float32_matmul_precision() == "highest"
    assert len({str(key) for key in keys.values()}) == 3
    assert_same_labels(labels["fp32"], labels["tf32"])
    for fp32, bf16 in zip(labels["fp32"], labels["bf16"]):
        assert bf16.max() > 0 and np.mean(fp32 != bf16) < 0.05
    points = np.array([[5.0, 6.0], [20.0, 12.0]])
    decoded = {}
    for precision in ("fp32", "bf16"):
        steps = SamSteps(SamPredictor(sam), precision)
        low_res, iou = steps.decode_points(steps.encode_crops([image])[0], points)
        assert low_res.dtype == iou.dtype == torch.float32 and low_res.shape[:2] == iou.shape == (2, 3)
        decoded[precision] = low_res
    assert not torch.equal(decoded["fp32"], decoded["bf16"])
    torch.testing.assert_close(decoded["bf16"], decoded["fp32"], rtol=0.05, atol=0.05)
    with pytest.raises(VoteSplatInputError, match="unknown SAM precision 'fp16'"):
        SamMaskSource(sam_model=sam, precision="fp16")


def test_default_sam_precision_is_bf16_on_a_gpu_with_bfloat16_and_fp32_on_a_cpu(monkeypatch):
    """``auto`` (the default) is decided when the source is made, so the cache key names the arithmetic that made
    the masks: a CPU's cache is not taken for a GPU's."""
    from votesplat_ns.core.sam_masks import SamMaskSource, default_sam_precision
    from votesplat_ns.ns.mask_settings import SamOptions

    sam = tiny_sam()
    assert SamOptions().sam_precision == "auto"
    assert default_sam_precision("cpu") == "fp32"
    assert SamMaskSource(sam_model=sam, device="cpu").config_key()["precision"] == "fp32"
    capability = {"cuda:0": 9, "cuda:1": 7}  # an H100 and a T4 (which only emulates bfloat16)
    asked = []

    def properties(device):
        asked.append(str(device))
        return SimpleNamespace(major=capability[str(device) if device.index is not None else "cuda:0"])

    monkeypatch.setattr(torch.cuda, "get_device_properties", properties)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # for the source's device check
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert default_sam_precision("cuda:0") == "bf16" and default_sam_precision("cuda:1") == "fp32"
    assert SamMaskSource(sam_model=sam, device="cuda").config_key()["precision"] == "bf16"
    assert asked == ["cuda:0", "cuda:1", "cuda"]


def test_a_sam_device_this_machine_lacks_is_refused_in_one_line(monkeypatch):
    """Before any model is built: a device name torch does not know, CUDA where there is none, a GPU index past the
    last GPU, MPS off a Mac; each line names both commands' flags."""
    from votesplat_ns.core.sam_masks import SamMaskSource, check_sam_device
    from votesplat_ns.errors import VoteSplatInputError

    sam = tiny_sam()
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    for device, why in (
        ("gpu0", "is not a device"),
        ("cuda", "CUDA is not available on this machine"),
        ("mps", "MPS (Apple GPU) is not available"),
    ):
        with pytest.raises(VoteSplatInputError, match=re.escape(why)) as refused:
            SamMaskSource(sam_model=sam, device=device)
        assert "--sam-device" in str(refused.value) and "--pipeline.datamanager.sam-device" in str(refused.value)
    check_sam_device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    check_sam_device("cuda:1")
    with pytest.raises(VoteSplatInputError, match=r"this machine has 2 GPUs \(cuda:0 to cuda:1\)"):
        check_sam_device("cuda:2")


def test_tf32_precision_is_held_while_any_thread_needs_it_and_restored_after_the_last():
    """tf32 sets torch's float32 matmul precision, which is global: with two threads inside at once, the one that
    leaves first must not restore it under the other."""
    import threading

    from votesplat_ns.core.sam_masks import _float32_matmul_precision

    first_inside, second_inside, first_left = threading.Event(), threading.Event(), threading.Event()
    seen = {}

    def first():
        with _float32_matmul_precision("high"):
            first_inside.set()
            second_inside.wait(5)
        first_left.set()

    def second():
        first_inside.wait(5)
        with _float32_matmul_precision("high"):
            second_inside.set()
            first_left.wait(5)
            seen["after the first left"] = torch.get_float32_matmul_precision()

    before = torch.get_float32_matmul_precision()
    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(10)
    assert seen == {"after the first left": "high"}
    assert torch.get_float32_matmul_precision() == before == "highest"


def test_masks_packed_to_bits_come_back_as_their_windows():
    from votesplat_ns.core.sam_masks import _MaskWindows, _packed_bits, _Window

    rng = np.random.default_rng(1)
    windows = _MaskWindows((40, 50))
    expected = {}
    for key in range(30):
        height, width = int(rng.integers(1, 30)), int(rng.integers(1, 41))
        mask = random_blob_mask(rng, (height, width)) if min(height, width) >= 8 else rng.random((height, width)) < 0.5
        packed = _packed_bits(torch.as_tensor(mask)[None]).numpy()[0]
        assert np.array_equal(packed, np.packbits(mask, axis=-1))
        rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
        box = np.array([cols[0], rows[0], cols[-1], rows[-1]]) if rows.size else np.zeros(4, dtype=np.int64)
        windows.add_packed(key, packed, box, (7, 3))
        expected[key] = mask if rows.size else np.zeros((1, 1), dtype=bool)
    for key, mask in expected.items():
        window = windows.original(key)
        full = np.zeros((40, 50), dtype=bool)
        full[3 : 3 + mask.shape[0], 7 : 7 + mask.shape[1]] = mask
        assert isinstance(window, _Window) and window.mask.dtype == bool
        assert np.array_equal(window.full((40, 50)), full), key


def test_sam_mask_source_runs_the_one_pass_generator(one_torch_thread):
    from votesplat_ns.core.mask_sources import SamMaskSource

    sam = tiny_sam()
    options = dict(points_per_side=4, pred_iou_thresh=0.0, stability_score_thresh=0.0, min_mask_region_area=20)
    source = SamMaskSource(sam_model=sam, device="cpu", levels=("m", "default", "s"), **options)
    image = blocks_image()
    labels = source.masks_for_image(image, "blocks.png", 0)
    assert isinstance(source._generator, SamLevelsMaskGenerator)
    settings = {**source.generator_kwargs}
    assert settings.pop("precision") == "fp32"  # the oracle is segment_anything's float32 model
    assert settings.pop("decoder") == "folded"  # the oracle runs segment_anything's own decoder
    expected = ReferenceGenerator(sam, None, ("m", "default", "s"), **settings).label_images(image)
    assert all(np.array_equal(a, b) for a, b in zip(expected, labels))
    assert labels[1].max() > 0


def test_sam_points_per_batch_reaches_the_generator_and_the_cache_key_and_a_bad_one_is_refused(one_torch_thread):
    """``--sam-points-per-batch`` (both commands' SamOptions): the decoder's batch, named in the cache key; the labels
    do not depend on it (the oracle tests above run batches of 4, 7 and 64); 0 is refused in one line naming both
    flags, before any model is built."""
    from votesplat_ns.core.mask_sources import SamMaskSource
    from votesplat_ns.errors import VoteSplatInputError
    from votesplat_ns.ns.mask_settings import SamOptions

    sam = tiny_sam()
    image = blocks_image()
    options = dict(sam_points_per_side=4, sam_pred_iou_thresh=0.0, sam_stability_score_thresh=0.0)
    labels, keys = [], []
    for batch in (5, 16):
        generator_options = SamOptions(sam_points_per_batch=batch, **options).sam_generator_options()
        # what make_mask_source("sam", sam_options=generator_options) makes, with the tiny model instead of a checkpoint
        source = SamMaskSource(sam_model=sam, device="cpu", levels=("m", "default"), **generator_options)
        keys.append(source.config_key())
        labels.append(source.masks_for_image(image, "blocks.png", 0))
        assert source._generator.points_per_batch == batch
    assert [key["points_per_batch"] for key in keys] == [5, 16]
    assert all(np.array_equal(a, b) for a, b in zip(*labels)) and labels[0][1].max() > 0
    assert SamOptions().sam_points_per_batch == 256 == SamMaskSource(sam_model=sam).config_key()["points_per_batch"]
    with pytest.raises(VoteSplatInputError) as refused:
        SamMaskSource(sam_model=sam, points_per_batch=0)
    line = str(refused.value)
    assert (
        "\n" not in line and "--pipeline.datamanager.sam-points-per-batch" in line and "--sam-points-per-batch" in line
    )


def test_images_asked_for_from_two_threads_get_their_own_labels(one_torch_thread):
    """Two threads at once (the cache build's overlap of one view's host work with the next one's device work):
    each image gets the labels it gets alone, in any interleaving."""
    from concurrent.futures import ThreadPoolExecutor

    sam = tiny_sam()
    options = dict(
        points_per_side=4, pred_iou_thresh=0.0, stability_score_thresh=0.0, crop_n_layers=1, min_mask_region_area=20
    )
    images = [np.roll(blocks_image(), shift, axis=1) for shift in (0, 5, 11, 17, 23, 29)]
    expected = [SamLevelsMaskGenerator(SamPredictor(sam), LEVELS, **options).label_images(image) for image in images]
    assert len({labels[0].tobytes() for labels in expected}) == len(images)  # each image its own labels
    generator = SamLevelsMaskGenerator(SamPredictor(sam), LEVELS, **options)
    with ThreadPoolExecutor(max_workers=2) as pool:
        together = list(pool.map(generator.label_images, images))
    for labels, want in zip(together, expected):
        assert_same_labels(want, labels)


def vit_b_predictor(sam):
    """A SamPredictor over random-init vit_b whose image features are a fixed random tensor of the encoder's output
    shape: both paths get the same features either way, and a vit_b encoder pass takes over a minute on a CI CPU
    (the encoder itself runs in the tiny-model test above). Prompt encoder and mask decoder are vit_b's."""

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
        points_per_batch=4,  # three decoder calls, the last with one prompt
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


def compiling_steps(sam, monkeypatch, compiled):
    """SamSteps whose decoder goes through its compiled path on the CPU (compiling is for CUDA devices), with
    ``torch.compile`` replaced by ``compiled(function) -> function``."""
    from votesplat_ns.core import sam_masks
    from votesplat_ns.core.sam_masks import SamSteps

    monkeypatch.setattr(torch, "compile", lambda function, **options: compiled(function))
    for name in ("_compiled_decode_multimask", "_compiled_stability_counts_and_boxes"):
        monkeypatch.setattr(sam_masks, name, functools.lru_cache(None)(getattr(sam_masks, name).__wrapped__))
    steps = SamSteps(SamPredictor(sam), compile_decoder=True)
    assert not steps.compile_decoder  # a CPU device: not compiled
    steps.compile_decoder = True
    return steps


def test_the_compiled_decoder_pads_a_short_batch_to_the_size_compiled_for(monkeypatch, one_torch_thread):
    sam = tiny_sam()
    image = blocks_image()
    options = dict(
        points_per_side=5, points_per_batch=7, pred_iou_thresh=0.0, stability_score_thresh=0.0, crop_n_layers=1
    )
    prompts_seen, masks_scored = [], []

    def compiled(function):
        def run(*arguments):
            if function.__name__ == "stability_counts_and_boxes":
                masks_scored.append(len(arguments[0]))
            else:
                prompts_seen.append(arguments[3].shape[0])  # sparse
            return function(*arguments)

        return run

    labels = SamLevelsMaskGenerator(compiling_steps(sam, monkeypatch, compiled), LEVELS, **options).label_images(image)
    assert set(prompts_seen) == {7}  # 25 points per crop: three batches of 7 and one of 4, padded
    assert sum(masks_scored) > 0  # the stability scores and boxes through their compiled path too
    assert_same_labels(SamLevelsMaskGenerator(SamPredictor(sam), LEVELS, **options).label_images(image), labels)


@pytest.mark.parametrize(
    "failing, what", [("decode_multimask", "decoder"), ("stability_counts_and_boxes", "stability scores")]
)
def test_what_cannot_be_compiled_runs_uncompiled_after_one_warning(monkeypatch, one_torch_thread, failing, what):
    sam = tiny_sam()
    image = blocks_image()
    options = dict(points_per_side=4, pred_iou_thresh=0.0, stability_score_thresh=0.0, crop_n_layers=1)
    failures = []

    def compiled(function):
        def run(*arguments):
            if function.__name__ == failing:
                failures.append(1)
                raise RuntimeError("no working C compiler\nsecond line")
            return function(*arguments)

        return run

    steps = compiling_steps(sam, monkeypatch, compiled)
    with pytest.warns(
        UserWarning, match=rf"SAM's {what} could not be compiled \(RuntimeError: no working C compiler\)"
    ):
        labels = SamLevelsMaskGenerator(steps, LEVELS, **options).label_images(image)
    assert failures == [1] and not steps.compile_decoder  # one failure turns both off
    assert_same_labels(SamLevelsMaskGenerator(SamPredictor(sam), LEVELS, **options).label_images(image), labels)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="torch.compile of the decoder runs on CUDA devices")
def test_the_compiled_decoder_on_cuda_gives_the_uncompiled_outputs():
    from segment_anything import sam_model_registry

    from votesplat_ns.core.sam_masks import SamSteps

    torch.manual_seed(0)
    sam = sam_model_registry["vit_b"](checkpoint=None).cuda().eval()
    image = np.ascontiguousarray(np.kron(blocks_image(), np.ones((8, 8, 1), dtype=np.uint8)))
    points = np.random.default_rng(0).uniform(0, 190, size=(64, 2))
    outputs = {}
    for compile_decoder in (False, True):
        steps = SamSteps(SamPredictor(sam), compile_decoder=compile_decoder)
        assert steps.compile_decoder == compile_decoder
        state = steps.encode_crops([image])[0]
        with torch.no_grad():
            outputs[compile_decoder] = [steps.decode_points(state, points[:n]) for n in (64, 40)]
    for (eager_masks, eager_iou), (masks, iou) in zip(outputs[False], outputs[True]):
        scale = eager_masks.abs().max()
        torch.testing.assert_close(masks, eager_masks, rtol=0, atol=1e-4 * scale)
        torch.testing.assert_close(iou, eager_iou, rtol=0, atol=1e-4)


def test_stability_and_boxes_equal_segment_anything_s():
    from segment_anything.utils.amg import batched_mask_to_box, calculate_stability_score

    from votesplat_ns.core.sam_masks import stability_and_boxes

    generator = torch.Generator().manual_seed(0)
    for m, h, w in ((7, 13, 29), (5, 40, 3), (2, 1, 1)):
        logits = 3.0 * torch.randn(m, h, w, generator=generator)
        logits[0] = -5.0  # empty at the threshold and at both offsets
        logits[-1, :, -1] = 0.5  # one column only: a box of width 1 on the last column (and all of it when w == 1)
        for threshold, offset in ((0.0, 1.0), (0.5, 0.25)):
            stability, boxes = stability_and_boxes(logits, threshold, offset)
            expected = calculate_stability_score(logits, threshold, offset)
            torch.testing.assert_close(stability, expected, rtol=0, atol=0, equal_nan=True)
            expected_boxes = batched_mask_to_box(logits > threshold)
            assert boxes.dtype == expected_boxes.dtype and torch.equal(boxes, expected_boxes)
            assert boxes[0].tolist() == [0, 0, 0, 0]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="torch.compile of the mask filters runs on CUDA devices")
def test_the_compiled_stability_and_boxes_on_cuda_equal_the_uncompiled_ones():
    from segment_anything import sam_model_registry

    from votesplat_ns.core.sam_masks import SamSteps, stability_and_boxes

    sam = sam_model_registry["vit_b"](checkpoint=None).cuda().eval()
    steps = SamSteps(SamPredictor(sam), compile_decoder=True)
    generator = torch.Generator(device="cuda").manual_seed(0)
    for m, h, w in ((37, 540, 960), (5, 540, 960), (11, 301, 517)):  # new counts and sizes reuse one compilation
        logits = 4.0 * torch.randn(m, h, w, generator=generator, device="cuda")
        logits[0] = -5.0
        for offset in (1.0, 0.5):
            stability, boxes = steps.stability_and_boxes(logits, offset)
            expected_stability, expected_boxes = stability_and_boxes(logits, steps.mask_threshold, offset)
            torch.testing.assert_close(stability, expected_stability, rtol=0, atol=0, equal_nan=True)
            assert torch.equal(boxes, expected_boxes)
    assert steps.compile_decoder and "stability" in steps._compiled_for


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
