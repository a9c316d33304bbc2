"""Inputs that would otherwise train silently wrong, refused (or read correctly) before training:
lossy label images, images nerfstudio's loader reads as wrong colours, camera models splatfacto
would take for pinholes. Each refusal is one line that names the file."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from votesplat_ns.core.image_files import read_image_rgb, read_label_png
from votesplat_ns.core.mask_sources import DatasetMaskSource, FolderMaskSource
from votesplat_ns.errors import VoteSplatInputError
from votesplat_ns.ns.datamanager import VoteDataManagerConfig, check_data_input

DEMO_SCENE = Path(__file__).resolve().parents[1] / "votesplat_ns" / "data" / "demo"


@pytest.fixture
def scene(tmp_path) -> Path:
    """A copy of the demo scene (images, label images, transforms.json) that a test may damage."""
    scene = tmp_path / "scene"
    for folder in ("images", "instances", "parts"):
        shutil.copytree(DEMO_SCENE / folder, scene / folder)
    shutil.copy(DEMO_SCENE / "transforms.json", scene / "transforms.json")
    return scene


def edit_transforms(scene: Path, edit) -> None:
    path = scene / "transforms.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


def rename_frame(meta: dict, old: str, new: str) -> None:
    """A frame's image renamed in transforms.json: its file_path and the split lists that name it."""
    for frame in meta["frames"]:
        if frame["file_path"] == old:
            frame["file_path"] = new
    for split in ("train", "val", "test"):
        names = meta.get(f"{split}_filenames")
        if names is not None:
            meta[f"{split}_filenames"] = [new if name == old else name for name in names]


def refusal(config: VoteDataManagerConfig) -> str:
    with pytest.raises(VoteSplatInputError) as caught:
        check_data_input(config)
    message = str(caught.value)
    assert "\n" not in message
    return message


def test_jpeg_label_image_is_refused_before_training_and_by_the_readers(scene):
    check_data_input(VoteDataManagerConfig(data=scene, mask_source="dataset"))
    label = scene / "instances" / "frame_00002.png"
    ids = np.array(Image.open(label))
    assert ids.max() > 1
    # a JPEG under the label's own .png name: only the file's header tells
    Image.fromarray(ids.astype(np.uint8)).save(label, format="JPEG", quality=95)
    decoded = np.array(Image.open(label)).astype(np.int32)
    assert np.any(decoded != ids)  # what training would have read: ids changed at the mask edges

    for source in ("dataset", "auto"):
        message = refusal(VoteDataManagerConfig(data=scene, mask_source=source))
        assert str(label) in message and "JPEG" in message and "PNG (lossless)" in message
    # masks from elsewhere: the dataset's label files are not read, so not checked
    check_data_input(VoteDataManagerConfig(data=scene, mask_source="sam"))

    with pytest.raises(VoteSplatInputError, match=r"label image .*frame_00002\.png is a JPEG file.*PNG \(lossless\)$"):
        read_label_png(label)
    image = read_image_rgb(scene / "images" / "frame_00002.png")
    with pytest.raises(VoteSplatInputError, match=r"frame_00002\.png is a JPEG file"):
        DatasetMaskSource(scene, levels=("instance",)).masks_for_image(image, scene / "images" / "frame_00002.png", 1)
    folder = scene.parent / "masks"
    (folder / "instance").mkdir(parents=True)
    shutil.copy(label, folder / "instance" / "frame_00002.png")
    with pytest.raises(VoteSplatInputError, match=r"masks/instance/frame_00002\.png is a JPEG file"):
        FolderMaskSource(folder).masks_for_image(image, scene / "images" / "frame_00002.png", 1)


def test_cmyk_image_is_read_as_rgb_by_the_plugin_and_refused_for_nerfstudio(scene):
    path = scene / "images" / "frame_00003.png"
    rgb = np.asarray(Image.open(path).convert("RGB"))
    cmyk_path = scene / "images" / "frame_00003.jpg"
    Image.fromarray(rgb).convert("CMYK").save(cmyk_path, format="JPEG", quality=100, subsampling=0)
    assert Image.open(cmyk_path).mode == "CMYK"
    # the plugin's reader (SAM's input, label sizes) converts it to the right colours
    read = read_image_rgb(cmyk_path)
    assert read.shape == rgb.shape
    assert np.abs(read.astype(int) - rgb.astype(int)).mean() < 3.0
    # nerfstudio's loader (np.array of the image) would read CMYK as RGBA: refused before training
    path.unlink()
    edit_transforms(scene, lambda meta: rename_frame(meta, "images/frame_00003.png", "images/frame_00003.jpg"))
    message = refusal(VoteDataManagerConfig(data=scene))
    assert str(cmyk_path) in message and "mode CMYK" in message and "convert it to RGB" in message


def test_sixteen_bit_grey_image_is_refused_grey_rgba_and_sixteen_bit_colour_are_read(scene):
    """What SAM and nerfstudio both read right passes the checks (SAM gets 8-bit RGB); a 16-bit grey image is refused
    with one line naming it, before anything is cached."""
    import cv2

    images = scene / "images"
    rgb = np.asarray(Image.open(images / "frame_00004.png").convert("RGB"))
    Image.fromarray(rgb).convert("L").save(images / "frame_00005.png")
    Image.fromarray(np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 200, np.uint8)], axis=-1)).save(
        images / "frame_00006.png"
    )
    deep_colour = rgb.astype(np.uint16) * 257 + 3
    cv2.imwrite(str(images / "frame_00007.png"), deep_colour[..., ::-1])  # a 48-bit PNG (OpenCV writes BGR)
    assert [Image.open(images / f"frame_0000{i}.png").mode for i in (5, 6, 7)] == ["L", "RGBA", "RGB"]
    check_data_input(VoteDataManagerConfig(data=scene, mask_source="sam"))
    assert np.array_equal(read_image_rgb(images / "frame_00006.png"), rgb)
    assert np.array_equal(read_image_rgb(images / "frame_00007.png"), rgb)  # the high byte of each value

    deep_grey = images / "frame_00004.png"
    Image.fromarray(rgb[..., 0].astype(np.uint16) * 257).save(deep_grey)
    assert Image.open(deep_grey).mode == "I;16"
    for source in ("sam", "dataset"):
        message = refusal(VoteDataManagerConfig(data=scene, mask_source=source))
        assert message.startswith(f"image {deep_grey} is a 16/32-bit single-channel image (PIL mode I;16)")
        assert "save it as an 8-bit RGB or greyscale image" in message and "\n" not in message


def test_palette_image_is_refused_for_nerfstudio(scene):
    path = scene / "images" / "frame_00004.png"
    Image.open(path).convert("RGB").convert("P", palette=Image.Palette.ADAPTIVE).save(path)
    message = refusal(VoteDataManagerConfig(data=scene))
    assert str(path) in message and "mode P" in message


@pytest.mark.parametrize("model", ["EQUIRECTANGULAR", "FISHEYE624", "ORTHOPHOTO", "VR180_L", "NO_SUCH_MODEL"])
def test_camera_models_splatfacto_would_train_as_pinholes_are_refused(scene, model):
    edit_transforms(scene, lambda meta: meta.update(camera_model=model))
    message = refusal(VoteDataManagerConfig(data=scene))
    assert str(scene / "transforms.json") in message and repr(model) in message
    assert "supported: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, OPENCV_FISHEYE" in message


def test_fisheye_without_distortion_is_refused_and_with_it_accepted(scene):
    edit_transforms(scene, lambda meta: meta.update(camera_model="OPENCV_FISHEYE"))  # k1..k4 all 0
    message = refusal(VoteDataManagerConfig(data=scene))
    assert str(scene / "transforms.json") in message and "OPENCV_FISHEYE with k1..k4 all 0" in message
    # nerfstudio undistorts a fisheye with its parameters (and the vote labels are warped alike)
    edit_transforms(scene, lambda meta: meta.update(k1=0.05, k2=-0.01))
    check_data_input(VoteDataManagerConfig(data=scene))

    # per-frame parameters, as nerfstudio reads them when the file gives none
    def per_frame(meta):
        for key in ("k1", "k2", "k3", "k4", "p1", "p2"):
            meta.pop(key)
        for frame in meta["frames"]:
            frame["k1"] = 0.05
        meta["frames"][5]["k1"] = 0.0

    edit_transforms(scene, per_frame)
    message = refusal(VoteDataManagerConfig(data=scene))
    fifth = json.loads((scene / "transforms.json").read_text())["frames"][5]["file_path"]
    assert f"frame 5 ({fifth})" in message
    edit_transforms(scene, lambda meta: meta["frames"][5].update(k1=0.05))
    check_data_input(VoteDataManagerConfig(data=scene))
    # the pinhole models stay accepted, with or without distortion
    for model in ("PINHOLE", "SIMPLE_RADIAL", "OPENCV"):
        edit_transforms(scene, lambda meta: meta.update(camera_model=model))
        check_data_input(VoteDataManagerConfig(data=scene))
