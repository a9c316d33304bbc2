"""Instance features, LERF text relevancy, click selection and per-Gaussian masks (votesplat_ns.core.semantics)."""

import hashlib
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from votesplat_ns.core import semantics
from votesplat_ns.core.semantics import (
    SMALLEST_OPEN_CLIP_MODEL,
    CheckpointNotFoundError,
    ClipEncoder,
    EncoderProtocol,
    InstanceFeatures,
    click_select,
    instance_crop,
    instance_features,
    isolate,
    lerf_relevancy,
    query_text,
    remove,
    select_instances,
)

# 2 bins per channel: bin = 4*(r high) + 2*(g high) + (b high).
COLOUR_BIN = {"red": 4, "green": 2, "blue": 1, "yellow": 6, "magenta": 5, "cyan": 3, "white": 7}
RGB = {"red": (220, 30, 30), "green": (30, 200, 40), "blue": (20, 40, 230), "yellow": (230, 220, 20)}


class ColourHistogramEncoder:
    """Deterministic test encoder: image feature = colour histogram of the non-black pixels.

    Black is skipped because masked-out and padding pixels of a crop are black. Text features come
    from a hand-made table: a colour word is its bin; LERF's negatives are the uniform histogram.
    """

    config = {"kind": "colour_histogram_test", "bins_per_channel": 2}

    def __init__(self):
        self.image_calls = 0

    def encode_images(self, crops):
        self.image_calls += 1
        rows = []
        for crop in crops:
            pixels = crop.reshape(-1, 3).astype(int)
            pixels = pixels[pixels.any(axis=1)]
            bins = 4 * (pixels[:, 0] >= 128) + 2 * (pixels[:, 1] >= 128) + (pixels[:, 2] >= 128)
            rows.append(torch.bincount(torch.as_tensor(bins), minlength=8).float())
        return F.normalize(torch.stack(rows), dim=-1)

    def encode_text(self, texts):
        rows = []
        for text in texts:
            vector = torch.zeros(8)
            words = [word for word in text.split() if word in COLOUR_BIN]
            if words:
                for word in words:
                    vector[COLOUR_BIN[word]] += 1.0
            else:
                vector[1:] = 1.0
            rows.append(vector)
        return F.normalize(torch.stack(rows), dim=-1)


def _scene_views():
    """Two 40x60 views with instances 0 (red), 1 (blue), 2 (yellow, tiny in view 0) and background."""
    images, maps = [], []
    for view in range(2):
        image = np.full((40, 60, 3), 90, dtype=np.uint8)  # grey background, bin 0 like black
        instance_map = np.full((40, 60), -1, dtype=np.int64)
        red_box = (slice(5, 25), slice(5, 20)) if view == 0 else (slice(10, 40), slice(0, 25))
        instance_map[red_box] = 0
        instance_map[20:35, 30:50] = 1
        if view == 0:
            instance_map[2:5, 55:58] = 2  # 9 pixels: below min_pixels
        else:
            instance_map[0:8, 40:60] = 2
        for instance, colour in ((0, "red"), (1, "blue"), (2, "yellow")):
            image[instance_map == instance] = RGB[colour]
        images.append(image)
        maps.append(instance_map)
    return images, maps


def test_colour_encoder_satisfies_protocol():
    assert isinstance(ColourHistogramEncoder(), EncoderProtocol)


def test_instance_crop_masks_neighbours_black_and_pads_to_square():
    image = np.zeros((10, 12, 3), dtype=np.uint8)
    image[...] = (10, 20, 30)
    mask = np.zeros((10, 12), dtype=bool)
    mask[2:5, 3:9] = True  # 3 rows x 6 cols box
    mask[2, 3] = False  # inside the box but not the instance
    image[mask] = (200, 0, 0)

    crop = instance_crop(image, mask, "masked_bbox")
    assert crop.shape == (6, 6, 3) and crop.dtype == np.uint8
    # Centred vertically: rows 0 and 4..5 are padding ((6 - 3) // 2 = 1 row above).
    assert (crop[0] == 0).all() and (crop[4:] == 0).all()
    assert (crop[1, 0] == 0).all()  # the masked-out neighbour pixel is black
    assert (crop[1, 1:] == (200, 0, 0)).all() and (crop[2:4] == (200, 0, 0)).all()

    context = instance_crop(image, mask, "bbox")
    assert (context[1, 0] == (10, 20, 30)).all()  # neighbour pixel kept as context
    with pytest.raises(ValueError, match="crop_mode"):
        instance_crop(image, mask, "square")
    with pytest.raises(ValueError, match="empty instance mask"):
        instance_crop(image, np.zeros_like(mask), "bbox")


def test_instance_features_use_pixel_count_weighted_mean_over_views():
    encoder = ColourHistogramEncoder()
    images, maps = _scene_views()
    feats = instance_features(images, maps, encoder, min_pixels=20)

    assert sorted(feats) == [0, 1, 2]
    for instance in feats:
        expected_sum = torch.zeros(8)
        pixels = views = 0
        for image, instance_map in zip(images, maps):
            mask = instance_map == instance
            if mask.sum() < 20:
                continue
            crop_feature = encoder.encode_images([instance_crop(image, mask, "masked_bbox")])[0]
            expected_sum += int(mask.sum()) * crop_feature
            pixels += int(mask.sum())
            views += 1
        assert torch.allclose(feats[instance], F.normalize(expected_sum, dim=0), atol=1e-6)
        assert feats.visible_pixels[instance] == pixels and feats.view_count[instance] == views
        assert math.isclose(float(feats[instance].norm()), 1.0, rel_tol=1e-6)
    # The 9-pixel glimpse of instance 2 in view 0 is below min_pixels and does not count.
    assert feats.view_count[2] == 1 and feats.visible_pixels[2] == int((maps[1] == 2).sum())
    assert feats.config["crop_mode"] == "masked_bbox" and feats.config["min_pixels"] == 20
    assert feats.config["encoder"] == ColourHistogramEncoder.config

    never_big_enough = instance_features(images[:1], maps[:1], encoder, min_pixels=20)
    assert 2 not in never_big_enough


def test_views_whose_features_cancel_are_dropped_with_a_warning():
    class OppositeEncoder(ColourHistogramEncoder):
        def __init__(self):
            self.sign = 1.0

        def encode_images(self, crops):
            self.sign = -self.sign
            return torch.full((len(crops), 8), self.sign) / math.sqrt(8)

    image = np.full((10, 10, 3), 200, dtype=np.uint8)
    instance_map = np.zeros((10, 10), dtype=np.int64)
    with pytest.warns(UserWarning, match="average to ~0"):
        feats = instance_features([image, image], [instance_map, instance_map], OppositeEncoder(), min_pixels=1)
    assert len(feats) == 0


def test_instance_features_reject_bad_input():
    encoder = ColourHistogramEncoder()
    images, maps = _scene_views()
    with pytest.raises(ValueError, match="one map per image"):
        instance_features(images, maps[:1], encoder)
    with pytest.raises(ValueError, match="resolution"):
        instance_features(images[:1], [maps[0][:, :30]], encoder)
    with pytest.raises(ValueError, match="uint8"):
        instance_features([images[0].astype(np.float32)], maps[:1], encoder)
    with pytest.raises(ValueError, match="integer"):
        instance_features(images[:1], [maps[0].astype(np.float32)], encoder)
    with pytest.raises(ValueError, match="crop_mode"):
        instance_features(images, maps, encoder, crop_mode="whole_image")
    with pytest.raises(ValueError, match="min_pixels"):
        instance_features(images, maps, encoder, min_pixels=0)
    with pytest.raises(ValueError, match="no views"):
        instance_features([], [], encoder)


def test_instance_features_save_load_round_trip_and_mismatch_checks(tmp_path):
    encoder = ColourHistogramEncoder()
    images, maps = _scene_views()
    feats = instance_features(images, maps, encoder, min_pixels=20, crop_mode="bbox")
    path = tmp_path / "features" / "instances.npz"
    feats.save(path)
    assert sorted(p.name for p in path.parent.iterdir()) == ["instances.npz"]  # no temp file left

    loaded = InstanceFeatures.load(path, encoder=encoder, crop_mode="bbox", min_pixels=20)
    assert sorted(loaded) == sorted(feats)
    for instance in feats:
        assert torch.equal(loaded[instance], feats[instance])
    assert loaded.config == feats.config
    assert loaded.visible_pixels == feats.visible_pixels and loaded.view_count == feats.view_count

    class OtherEncoder(ColourHistogramEncoder):
        config = {"kind": "colour_histogram_test", "bins_per_channel": 3}

    with pytest.raises(ValueError, match="bins_per_channel: 2 vs 3"):
        InstanceFeatures.load(path, encoder=OtherEncoder())
    with pytest.raises(ValueError, match="crop_mode='bbox', expected 'masked_bbox'"):
        InstanceFeatures.load(path, crop_mode="masked_bbox")
    with pytest.raises(ValueError, match="different encoder"):
        query_text("red", loaded, OtherEncoder())
    with pytest.raises(ValueError, match="not found"):
        InstanceFeatures.load(tmp_path / "missing.npz")


def test_lerf_relevancy_is_min_over_negatives_of_pairwise_softmax():
    x = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    positive = torch.tensor([1.0, 0.0])
    negatives = torch.tensor([[0.0, 1.0], [0.6, 0.8]])
    relevancy = lerf_relevancy(x, positive, negatives, scale=10.0)

    def pairwise(pos_sim, neg_sim):
        return math.exp(10 * pos_sim) / (math.exp(10 * pos_sim) + math.exp(10 * neg_sim))

    expected_first = min(pairwise(1.0, 0.0), pairwise(1.0, 0.6))
    expected_second = min(pairwise(0.0, 1.0), pairwise(0.0, 0.8))
    assert relevancy.tolist() == pytest.approx([expected_first, expected_second], rel=1e-6)
    with pytest.raises(ValueError, match="negative"):
        lerf_relevancy(x, positive, torch.zeros(0, 2))
    with pytest.raises(ValueError, match="scale"):
        lerf_relevancy(x, positive, negatives, scale=0.0)


def test_text_query_ranks_the_matching_instance_first():
    encoder = ColourHistogramEncoder()
    images, maps = _scene_views()
    feats = instance_features(images, maps, encoder, min_pixels=20)

    for word, instance in (("red", 0), ("blue", 1), ("yellow", 2)):
        ranked = query_text(f"{word} thing", feats, encoder)
        assert [i for i, _ in ranked][0] == instance
        assert [r for _, r in ranked] == sorted((r for _, r in ranked), reverse=True)
        assert all(0.0 < r < 1.0 for _, r in ranked)
        assert ranked[0][1] > 0.9 and ranked[1][1] < 0.1
        assert select_instances(ranked) == [instance]
        assert select_instances(ranked, threshold=0.5) == [instance]
    ranked = query_text("green", feats, encoder)
    assert select_instances(ranked, threshold=0.5) == []  # nothing green in the scene


def test_text_query_rejects_bad_input():
    encoder = ColourHistogramEncoder()
    images, maps = _scene_views()
    feats = instance_features(images, maps, encoder, min_pixels=20)
    for empty in ("", "   "):
        with pytest.raises(ValueError, match="empty"):
            query_text(empty, feats, encoder)
    with pytest.raises(ValueError, match="no instance features"):
        query_text("red", {}, encoder)
    with pytest.raises(ValueError, match="not a single string"):
        query_text("red", feats, encoder, negatives="object")
    with pytest.raises(ValueError, match="negatives"):
        query_text("red", feats, encoder, negatives=())
    with pytest.raises(ValueError, match="logit_scale"):
        query_text("red", feats, encoder, scale=None)
    with pytest.raises(ValueError, match="threshold"):
        select_instances([(0, 0.9)], threshold=1.5)
    with pytest.raises(ValueError, match="empty"):
        select_instances([])
    with pytest.raises(ValueError, match="dimension"):
        query_text("red", {0: torch.ones(5)}, encoder)


@pytest.fixture(scope="module")
def random_clip():
    return ClipEncoder.random_init(SMALLEST_OPEN_CLIP_MODEL, device="cpu", seed=0)


def test_random_open_clip_encoder_wiring(random_clip):
    assert isinstance(random_clip, EncoderProtocol)
    images, maps = _scene_views()
    crops = [instance_crop(images[1], maps[1] == i) for i in range(3)]
    image_features = random_clip.encode_images(crops)
    text_features = random_clip.encode_text(["red apple", "a blue cup"])
    dim = random_clip.model.text_projection.shape[1]
    assert image_features.shape == (3, dim) and text_features.shape == (2, dim)
    assert image_features.dtype == torch.float32
    assert torch.allclose(image_features.norm(dim=-1), torch.ones(3), atol=1e-5)
    assert torch.allclose(text_features.norm(dim=-1), torch.ones(2), atol=1e-5)

    # Same seed, same weights, and eval mode (no dropout), so the same features; the global RNG is untouched.
    assert not random_clip.model.training
    rng_state = torch.random.get_rng_state()
    again = ClipEncoder.random_init(SMALLEST_OPEN_CLIP_MODEL, seed=0)
    assert torch.equal(torch.random.get_rng_state(), rng_state)
    again_weights = again.model.state_dict()
    assert all(torch.equal(tensor, again_weights[name]) for name, tensor in random_clip.model.state_dict().items())

    feats = instance_features(images, maps, random_clip, min_pixels=20)
    ranked = query_text("red apple", feats, random_clip)
    assert sorted(i for i, _ in ranked) == [0, 1, 2]
    assert all(0.0 < r < 1.0 for _, r in ranked)
    # scale=None uses CLIP's own logit scale.
    with_logit_scale = dict(query_text("red apple", feats, random_clip, scale=None))
    ids, matrix = feats.matrix()
    phrases = random_clip.encode_text(["red apple", *semantics.DEFAULT_NEGATIVES])
    expected = lerf_relevancy(matrix, phrases[0], phrases[1:], random_clip.logit_scale)
    assert [with_logit_scale[i] for i in ids] == pytest.approx(expected.tolist(), rel=1e-5)
    with pytest.raises(ValueError, match="non-empty"):
        random_clip.encode_text(["red", ""])
    with pytest.raises(ValueError, match="uint8"):
        random_clip.encode_images([np.zeros((4, 4), dtype=np.uint8)])


def test_clip_checkpoint_loads_from_a_local_file_only(tmp_path, random_clip):
    checkpoint = tmp_path / "clip_weights.pt"
    torch.save(random_clip.model.state_dict(), checkpoint)
    loaded = ClipEncoder.from_checkpoint(SMALLEST_OPEN_CLIP_MODEL, checkpoint, device="cpu")
    assert loaded.config["checkpoint_sha256"] == hashlib.sha256(checkpoint.read_bytes()).hexdigest()
    assert loaded.config["checkpoint_path"] == str(checkpoint.resolve())
    texts = ["a red toy chair", "spatula"]
    assert torch.allclose(loaded.encode_text(texts), random_clip.encode_text(texts), atol=1e-5)

    # The same weights under another folder are the same feature space; other weights are not.
    semantics.check_same_encoder({**loaded.config, "checkpoint_path": "/elsewhere/clip_weights.pt"}, loaded)
    with pytest.raises(ValueError, match="checkpoint_sha256"):
        semantics.check_same_encoder({**loaded.config, "checkpoint_sha256": "0" * 64}, loaded)
    with pytest.raises(ValueError, match="kind"):
        semantics.check_same_encoder(loaded.config, random_clip)

    missing = tmp_path / "ViT-B-16.bin"
    with pytest.raises(CheckpointNotFoundError, match="CLIP checkpoint not found") as error:
        ClipEncoder.from_checkpoint("ViT-B-16", missing)
    assert str(missing) in str(error.value) and isinstance(error.value, ValueError)
    assert "\n" not in str(error.value)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"these are not weights")
    with pytest.raises(
        ValueError, match=r"does not hold open_clip weights .*\(it is not a PyTorch weights file\)"
    ) as error:
        ClipEncoder.from_checkpoint(SMALLEST_OPEN_CLIP_MODEL, garbage)
    assert "weights_only" not in str(error.value)  # torch's advice to unpickle an unknown file is not relayed
    other = tmp_path / "other_weights.pt"
    torch.save({"visual.proj": torch.zeros(3)}, other)
    with pytest.raises(ValueError, match=r"\(it holds weights of another model\)"):
        ClipEncoder.from_checkpoint(SMALLEST_OPEN_CLIP_MODEL, other)
    with pytest.raises(ValueError, match="hub"):
        ClipEncoder.from_checkpoint("hf-hub:laion/CLIP-ViT-B-32", checkpoint)
    with pytest.raises(ValueError, match="unknown open_clip architecture"):
        ClipEncoder.from_checkpoint("ViT-Nonexistent", checkpoint)
    with pytest.raises(ValueError, match="Hugging Face"):
        ClipEncoder.random_init("ViT-B-16-SigLIP")


def test_text_longer_than_clip_reads_is_refused(random_clip):
    fits = " ".join(["mug"] * 75)  # one token each: exactly the 75 the context holds besides start and end
    random_clip.check_text_length([fits])
    assert random_clip.encode_text([fits]).shape[0] == 1
    with pytest.raises(
        ValueError,
        match=r"^the text 'mug mug .*\.\.\.' \(303 characters\) is 76 tokens long, but CLIP reads at most 75",
    ):
        random_clip.encode_text([fits + " mug"])


def test_click_select_maps_continuous_pixel_coordinates_to_ids():
    instance_map = np.array(
        [
            [-1, -1, 3, 3],
            [-1, 5, 5, 3],
            [7, 7, -1, -1],
        ]
    )
    height, width = instance_map.shape
    for row in range(height):
        for col in range(width):
            expected = None if instance_map[row, col] < 0 else int(instance_map[row, col])
            assert click_select(instance_map, col, row) == expected  # integer = that pixel
            assert click_select(instance_map, col + 0.5, row + 0.5) == expected  # its centre
            assert click_select(instance_map, col + 0.999, row + 0.001) == expected
    assert click_select(torch.as_tensor(instance_map), 1.2, 1.7) == 5
    for x, y in ((width, 0), (0, height), (-0.01, 1), (1, -3), (float("nan"), 1), (1, float("inf"))):
        with pytest.raises(ValueError, match="outside|finite"):
            click_select(instance_map, x, y)
    with pytest.raises(ValueError, match=r"\[H, W\]"):
        click_select(instance_map[None], 0, 0)
    with pytest.raises(ValueError, match="integer"):
        click_select(instance_map.astype(float), 0, 0)


def test_isolate_and_remove_give_complementary_gaussian_masks():
    ids = torch.tensor([0, 1, -1, 1, 2, 0, -1])
    assert isolate(ids, 1).tolist() == [False, True, False, True, False, False, False]
    assert remove(ids, 1).tolist() == [True, False, True, False, True, True, True]
    assert isolate(ids, [0, 2]).tolist() == [True, False, False, False, True, True, False]
    assert torch.equal(remove(ids, [0, 2]), ~isolate(ids, [0, 2]))

    as_numpy = isolate(ids.numpy(), 2)
    assert isinstance(as_numpy, np.ndarray) and as_numpy.dtype == bool and as_numpy.sum() == 1

    # A click on the background selects nothing: that is an error to act on, not an empty mask.
    with pytest.raises(ValueError, match="nothing selected"):
        isolate(ids, click_select(np.array([[-1]]), 0, 0))
    with pytest.raises(ValueError, match="own no Gaussian"):
        remove(ids, [1, 9])
    with pytest.raises(ValueError, match="negative"):
        isolate(ids, -1)
    with pytest.raises(ValueError, match="empty"):
        isolate(ids, [])
    with pytest.raises(ValueError, match="1-D integer"):
        isolate(ids.float(), 1)
