"""Mask sources: folder of label PNGs, the dataset's label images, SAM (tiny random model, real generator)."""

import json
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from votesplat_ns.core.mask_sources import (
    SAM_CHECKPOINT_FILES,
    DatasetMaskSource,
    FolderMaskSource,
    SamMaskSource,
    check_label_size,
    make_mask_source,
    read_image_rgb,
    read_label_png,
)


def write_png(path: Path, array: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(array).save(path)
    return path


def rgb_image(height=24, width=32, seed=0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)


# ------------------------------------------------------------------------------- folder
def test_folder_source_reads_8_and_16_bit_pngs(tmp_path):
    parts = np.zeros((24, 32), dtype=np.uint16)
    parts[3:9, 4:10] = 300  # needs 16 bits
    objects = np.zeros((24, 32), dtype=np.uint8)
    objects[10:20, 5:25] = 7
    write_png(tmp_path / "masks" / "part" / "frame_001.png", parts)
    write_png(tmp_path / "masks" / "object" / "frame_001.png", objects)
    source = FolderMaskSource(tmp_path / "masks")
    assert source.levels == ("object", "part")  # sorted sub-folders
    labels = source.masks_for_image(rgb_image(), tmp_path / "images" / "frame_001.jpg", 0)
    assert [lab.dtype for lab in labels] == [np.int32, np.int32]
    assert np.array_equal(labels[0], objects) and np.array_equal(labels[1], parts)
    assert source.config_key() == {"type": "folder", "levels": ["object", "part"]}

    before = source.view_fingerprint(tmp_path / "images" / "frame_001.jpg", 0)
    parts[0, 0] = 1
    write_png(tmp_path / "masks" / "part" / "frame_001.png", parts)
    assert source.view_fingerprint(tmp_path / "images" / "frame_001.jpg", 0) != before


def test_folder_source_leaves_out_hidden_folders(tmp_path):
    for level in ("instance", "part", ".ipynb_checkpoints", "__pycache__"):
        write_png(tmp_path / "m" / level / "a.png", np.zeros((24, 32), np.uint16))
    assert FolderMaskSource(tmp_path / "m").levels == ("instance", "part")
    # named explicitly, a hidden folder is still a level: only the default listing leaves them out
    assert FolderMaskSource(tmp_path / "m", levels=(".ipynb_checkpoints",)).levels == (".ipynb_checkpoints",)


def test_broken_image_files_are_named(tmp_path):
    good = write_png(tmp_path / "good.png", rgb_image())
    assert read_image_rgb(good).shape == (24, 32, 3)
    data = good.read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"^image .*cut\.png cannot be read \(the file is truncated.*; replace it"):
        read_image_rgb(tmp_path / "cut.png")
    (tmp_path / "text.png").write_text("hello")
    with pytest.raises(ValueError, match=r"^image .*text\.png cannot be read \(not an image format PIL can read\)"):
        read_image_rgb(tmp_path / "text.png")
    labels = write_png(tmp_path / "labels.png", np.ones((24, 32), np.uint16))
    (tmp_path / "cut_labels.png").write_bytes(labels.read_bytes()[:60])
    with pytest.raises(ValueError, match=r"^label image .*cut_labels\.png cannot be read"):
        read_label_png(tmp_path / "cut_labels.png")
    with pytest.raises(ValueError, match=r"^label image .*absent\.png does not exist"):
        read_label_png(tmp_path / "absent.png")


def test_folder_source_errors_name_the_file(tmp_path):
    write_png(tmp_path / "m" / "instance" / "a.png", np.zeros((24, 32), np.uint16))
    write_png(tmp_path / "m" / "part" / "a.png", np.zeros((20, 32), np.uint16))  # wrong size
    (tmp_path / "m" / "part" / "b.png").parent.mkdir(exist_ok=True)
    write_png(tmp_path / "m" / "instance" / "b.png", np.zeros((24, 32), np.uint16))  # part/b.png missing
    write_png(tmp_path / "m" / "instance" / "c.png", np.zeros((24, 32, 3), np.uint8))  # RGB
    source = FolderMaskSource(tmp_path / "m", levels=("instance", "part"))

    with pytest.raises(ValueError) as error:
        source.masks_for_image(rgb_image(), "images/a.jpg", 0)
    message = str(error.value)
    assert "part/a.png" in message and "32x20" in message and "32x24" in message and "\n" not in message

    with pytest.raises(ValueError, match=r"missing label image .*part/b\.png"):
        source.masks_for_image(rgb_image(), "images/b.jpg", 1)
    with pytest.raises(ValueError, match=r"instance/c\.png .*single-channel"):
        source.masks_for_image(rgb_image(), "images/c.jpg", 2)
    with pytest.raises(ValueError, match="no sub-folder 'depth'"):
        FolderMaskSource(tmp_path / "m", levels=("instance", "depth"))
    with pytest.raises(ValueError, match="does not exist"):
        FolderMaskSource(tmp_path / "nowhere")


def test_label_size_accepts_uniform_scaling_only():
    check_label_size((24, 32), (24, 32), "x")
    check_label_size((24, 32), (12, 16), "x")  # images_2
    check_label_size((667, 1001), (83, 125), "x")  # images_8 with rounding
    with pytest.raises(ValueError, match="32x20"):
        check_label_size((20, 32), (12, 16), "x")


# ------------------------------------------------------------------------------ dataset
def test_dataset_source_reads_frame_label_paths_and_matches_downscaled_images(tmp_path):
    instance = np.zeros((24, 32), dtype=np.uint16)
    instance[4:12, 6:14] = 1
    part = np.zeros((24, 32), dtype=np.uint16)
    part[4:8, 6:14] = 2
    write_png(tmp_path / "instances" / "f1.png", instance)
    write_png(tmp_path / "parts" / "f1.png", part)
    meta = {
        "frames": [
            {"file_path": "images/f1.png", "instance_mask_path": "instances/f1.png", "part_mask_path": "parts/f1.png"}
        ]
    }
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    assert DatasetMaskSource.has_masks(tmp_path)

    source = DatasetMaskSource(tmp_path)
    labels = source.masks_for_image(rgb_image(), tmp_path / "images" / "f1.png", 0)
    assert np.array_equal(labels[0], instance) and np.array_equal(labels[1], part)
    # nerfstudio's images_2/ copy is matched by file name; labels stay at full resolution
    labels_2 = source.masks_for_image(rgb_image(12, 16), tmp_path / "images_2" / "f1.png", 0)
    assert labels_2[0].shape == (24, 32)
    with pytest.raises(ValueError, match="not a frame"):
        source.masks_for_image(rgb_image(), tmp_path / "images" / "other.png", 0)
    assert isinstance(make_mask_source("auto", data=tmp_path), DatasetMaskSource)

    meta["frames"].append({"file_path": "images/f2.png", "instance_mask_path": "instances/f2.png"})
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="no 'part_mask_path'"):
        DatasetMaskSource(tmp_path)


def test_read_label_png_rejects_missing_file(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        read_label_png(tmp_path / "nope.png")


# ---------------------------------------------------------------------------------- SAM
def tiny_sam(seed: int = 0):
    """A randomly initialised SAM with a 1-block ViT on 64x64 inputs (~70k parameters)."""
    from segment_anything.modeling import ImageEncoderViT, MaskDecoder, PromptEncoder, Sam, TwoWayTransformer

    torch.manual_seed(seed)
    image_size, patch, dim = 64, 16, 32
    grid = image_size // patch
    return Sam(
        image_encoder=ImageEncoderViT(
            img_size=image_size,
            patch_size=patch,
            embed_dim=32,
            depth=1,
            num_heads=2,
            mlp_ratio=2,
            out_chans=dim,
            qkv_bias=True,
            norm_layer=partial(torch.nn.LayerNorm, eps=1e-6),
            use_rel_pos=True,
            window_size=0,
            global_attn_indexes=(0,),
        ),
        prompt_encoder=PromptEncoder(
            embed_dim=dim, image_embedding_size=(grid, grid), input_image_size=(image_size, image_size), mask_in_chans=4
        ),
        mask_decoder=MaskDecoder(
            num_multimask_outputs=3,
            transformer=TwoWayTransformer(depth=1, embedding_dim=dim, mlp_dim=64, num_heads=2),
            transformer_dim=dim,
            iou_head_depth=2,
            iou_head_hidden_dim=32,
        ),
    ).eval()


def blocks_image() -> np.ndarray:
    image = np.full((24, 32, 3), 40, dtype=np.uint8)
    image[4:14, 3:13] = (220, 30, 30)
    image[8:20, 16:29] = (30, 200, 60)
    return image


def test_sam_source_end_to_end_with_tiny_random_sam(one_torch_thread):
    sam = tiny_sam()
    options = dict(
        points_per_side=3, pred_iou_thresh=0.0, stability_score_thresh=0.0, crop_n_layers=0, min_mask_region_area=0
    )
    source = SamMaskSource(sam_model=sam, device="cpu", **options)
    assert source.levels == ("default", "s", "m", "l")
    image = blocks_image()
    labels = source.masks_for_image(image, "blocks.png", 0)
    assert len(labels) == 4
    for level in labels:
        assert level.shape == (24, 32) and level.dtype == np.int32 and level.min() >= 0
    # thresholds at zero: the real generator keeps masks at every level
    assert all(level.max() > 0 for level in labels)

    # deterministic, and a subset of levels reproduces the same per-level output
    only_m = SamMaskSource(sam_model=sam, device="cpu", levels=("m", "default"), **options)
    again = only_m.masks_for_image(image, "blocks.png", 0)
    assert np.array_equal(again[0], labels[2]) and np.array_equal(again[1], labels[0])
    # the cache key changes with the arguments and with the weights
    assert only_m.config_key() != source.config_key()
    assert SamMaskSource(sam_model=tiny_sam(seed=1), device="cpu", **options).config_key() != source.config_key()

    # large images are downscaled before SAM
    small = SamMaskSource(sam_model=sam, device="cpu", levels=("default",), max_long_side=16, **options)
    assert small.masks_for_image(image, "blocks.png", 0)[0].shape == (12, 16)


def test_sam_source_view_without_any_mask_gives_empty_labels(one_torch_thread):
    # with crops, segment_anything 1.0 itself crashes in its cross-crop NMS when no crop keeps a mask
    sam = tiny_sam()
    options = dict(
        points_per_side=2, pred_iou_thresh=2.0, stability_score_thresh=0.0, crop_n_layers=1, min_mask_region_area=0
    )
    source = SamMaskSource(sam_model=sam, device="cpu", levels=("default", "m"), **options)
    labels = source.masks_for_image(blocks_image(), "blocks.png", 0)
    assert [level.shape for level in labels] == [(24, 32), (24, 32)]
    assert all(level.max() == 0 for level in labels)
    # and with crops and masks kept, the cross-crop NMS still runs
    kept = SamMaskSource(sam_model=sam, device="cpu", levels=("default",), **{**options, "pred_iou_thresh": 0.0})
    assert kept.masks_for_image(blocks_image(), "blocks.png", 0)[0].max() > 0


def test_missing_sam_checkpoint_error_names_the_expected_file(tmp_path):
    with pytest.raises(ValueError) as error:
        SamMaskSource(checkpoint=tmp_path / "sam_vit_h_4b8939.pth", model_type="vit_h")
    message = str(error.value)
    assert "sam_vit_h_4b8939.pth" in message and "facebookresearch/segment-anything" in message
    assert "does not exist" in message and "\n" not in message

    with pytest.raises(ValueError, match="sam_vit_b_01ec64.pth"):
        SamMaskSource(checkpoint=None, model_type="vit_b")
    with pytest.raises(ValueError, match="does not exist"):
        SamMaskSource(checkpoint=tmp_path, model_type="vit_l")  # a folder is not a checkpoint
    with pytest.raises(ValueError, match="unknown SAM model type"):
        SamMaskSource(checkpoint=None, model_type="vit_x")
    assert set(SAM_CHECKPOINT_FILES) == {"vit_h", "vit_l", "vit_b"}


def test_broken_sam_checkpoint_fails_with_one_line(tmp_path):
    broken = tmp_path / "sam_vit_b_01ec64.pth"
    broken.write_bytes(b"not a checkpoint")
    source = SamMaskSource(checkpoint=broken, model_type="vit_b", device="cpu")
    assert source.config_key()["checkpoint_name"] == "sam_vit_b_01ec64.pth"
    with pytest.raises(
        ValueError, match=r"could not load SAM checkpoint .*sam_vit_b_01ec64\.pth .*not a PyTorch weights file"
    ) as error:
        source.masks_for_image(blocks_image(), "blocks.png", 0)
    assert "weights_only" not in str(error.value)


def test_sam_checkpoint_of_another_model_or_truncated_fails_with_one_line(tmp_path):
    checkpoint = tmp_path / "sam_vit_b_01ec64.pth"
    torch.save(tiny_sam().state_dict(), checkpoint)  # weights, but not vit_b's
    with pytest.raises(ValueError) as error:
        SamMaskSource(checkpoint=checkpoint, model_type="vit_b", device="cpu").masks_for_image(
            blocks_image(), "a.png", 0
        )
    message = str(error.value)
    assert f"could not load SAM checkpoint {checkpoint} as model type 'vit_b'" in message
    assert "weights of another model" in message and "\n" not in message

    checkpoint.write_bytes(checkpoint.read_bytes()[: checkpoint.stat().st_size // 2])
    with pytest.raises(ValueError, match=r"sam_vit_b_01ec64\.pth as model type 'vit_b' \(the file is truncated"):
        SamMaskSource(checkpoint=checkpoint, model_type="vit_b", device="cpu").masks_for_image(
            blocks_image(), "a.png", 0
        )


def test_images_for_sam_grey_and_rgba_are_converted_16_bit_grey_is_refused(tmp_path):
    grey = rgb_image()[..., 0]
    assert np.array_equal(read_image_rgb(write_png(tmp_path / "grey.png", grey)), np.repeat(grey[..., None], 3, -1))
    rgba = np.concatenate([rgb_image(), np.full((24, 32, 1), 7, np.uint8)], axis=-1)
    assert np.array_equal(read_image_rgb(write_png(tmp_path / "rgba.png", rgba)), rgba[..., :3])
    deep = write_png(tmp_path / "deep.png", (np.arange(24 * 32).reshape(24, 32) * 80).astype(np.uint16))
    with pytest.raises(ValueError, match=r"^image .*deep\.png is a 16/32-bit single-channel image .*8-bit RGB"):
        read_image_rgb(deep)
