"""VoteDataManager on a tiny nerfstudio dataset: vote maps aligned with the training images; votesplat masks."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from PIL import Image

from votesplat_ns.cli.masks_cli import MasksConfig, main as masks_main
from votesplat_ns.core.vote_maps import round_half_away_from_zero
from votesplat_ns.ns.datamanager import VoteDataManagerConfig, default_cache_dir, place_vote_batch

WIDTH, HEIGHT, FRAMES = 32, 24, 3
BORDER_ID = 3  # the instance id that touches the image border in every frame


def look_at_origin(position) -> list:
    """camera-to-world (OpenGL convention: camera looks along -z) looking at the origin."""
    position = np.asarray(position, dtype=np.float64)
    forward = -position / np.linalg.norm(position)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, up, -forward, position
    return pose.tolist()


def frame_labels(i: int):
    instance = np.zeros((HEIGHT, WIDTH), dtype=np.uint16)
    instance[3 + i : 11 + i, 4:12] = 1
    instance[12:20, 15 + i : 27] = 2
    instance[0:4, 20:26] = BORDER_ID  # touches the top row
    part = np.zeros((HEIGHT, WIDTH), dtype=np.uint16)
    part[3 + i : 7 + i, 4:12] = 1
    part[7 + i : 11 + i, 4:12] = 2
    part[14:18, 18:24] = 4
    return instance, part


INSTANCE_CODE = 60  # red value per instance id in the images, so a warped image shows where the masks went


def make_dataset(root: Path, k1: float = 0.0) -> Path:
    rng = np.random.default_rng(0)
    frames = []
    for i in range(FRAMES):
        name = f"frame_{i:05d}.png"
        instance, part = frame_labels(i)
        image = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
        image[..., 0] = instance * INSTANCE_CODE
        for folder, array in (("images", image), ("images_2", image[::2, ::2])):
            (root / folder).mkdir(parents=True, exist_ok=True)
            Image.fromarray(array).save(root / folder / name)
        for folder, array in (("instances", instance), ("parts", part)):
            (root / folder).mkdir(parents=True, exist_ok=True)
            Image.fromarray(array).save(root / folder / name)
        frames.append(
            {
                "file_path": f"images/{name}",
                "transform_matrix": look_at_origin([3.0 * np.cos(i), 3.0 * np.sin(i), 1.0]),
                "instance_mask_path": f"instances/{name}",
                "part_mask_path": f"parts/{name}",
            }
        )
    meta = {
        "camera_model": "OPENCV",
        "fl_x": 30.0,
        "fl_y": 30.0,
        "cx": WIDTH / 2,
        "cy": HEIGHT / 2,
        "w": WIDTH,
        "h": HEIGHT,
        "k1": k1,
        "k2": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        "frames": frames,
    }
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def setup_manager(data: Path, cache_dir: Path, downscale: int = 1, **overrides):
    config = VoteDataManagerConfig(
        data=data,
        dataparser=NerfstudioDataParserConfig(downscale_factor=downscale, eval_mode="all"),
        cache_dir=cache_dir,
        cache_images="gpu",  # "gpu" caching just moves to the manager's device (cpu here); "cpu" pins memory
        cache_images_type="uint8",
        **overrides,
    )
    return config.setup(device="cpu", test_mode="val")


def expected_centroids(labels: np.ndarray) -> dict:
    out = {}
    for k in np.unique(labels[labels > 0]):
        rows, cols = np.nonzero(labels == k)
        out[int(k)] = round_half_away_from_zero(np.array([cols.mean(), rows.mean()]))
    return out


def renumbered_parts(part: np.ndarray) -> np.ndarray:
    """Part ids {1, 2, 4} as the vote maps number them: compactly, {1, 2, 3}."""
    return np.where(part == 4, 3, part).astype(np.int64)


def frame_number(manager, index: int) -> int:
    return int(Path(manager.train_dataset.image_filenames[index]).stem.split("_")[1])


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("capture"))


def test_next_train_gives_vote_maps_equal_to_the_label_files(dataset, tmp_path):
    manager = setup_manager(dataset, tmp_path / "cache", border_masks="drop")
    assert manager.vote_levels == ("instance", "part")
    seen = set()
    for step in range(FRAMES):
        camera, data = manager.next_train(step)
        index = int(camera.metadata["cam_idx"])
        seen.add(index)
        labels, centroids = data["vote_labels"], data["vote_centroids"]
        # compact: int16 ids and int32 pixel indices (half the bytes kept per view and copied per vote step)
        assert labels.dtype == torch.int16 and centroids.dtype == torch.float32
        assert data["vote_pixels"].dtype == torch.int32
        # host tensors (cache_vote_maps "cpu"): the model copies them to its device only on the steps that vote
        assert labels.device.type == "cpu" and centroids.device.type == "cpu"
        assert labels.shape == (2, *data["image"].shape[:2]) == (2, HEIGHT, WIDTH)
        instance, part = frame_labels(frame_number(manager, index))
        # ids 1, 2 keep their numbers; the border-touching id 3 is dropped (border_masks="drop")
        assert np.array_equal(labels[0].numpy(), np.where(instance == BORDER_ID, 0, instance))
        # part ids {1, 2, 4} are renumbered compactly to {1, 2, 3}
        assert np.array_equal(labels[1].numpy(), renumbered_parts(part))
        assert centroids.shape == (2, 4, 2) and torch.isnan(centroids[:, 0]).all()
        assert torch.isnan(centroids[0, 3]).all()  # level 0 has 2 masks: padded
        # the pixels training samples from: those inside a kept mask at some level, in raster order
        in_a_mask = ((labels[0] > 0) | (labels[1] > 0)).reshape(-1)
        assert torch.equal(data["vote_pixels"], torch.nonzero(in_a_mask).squeeze(1).to(torch.int32))
        for level, file_labels in ((0, np.where(instance == BORDER_ID, 0, instance)), (1, renumbered_parts(part))):
            for k, centre in expected_centroids(file_labels).items():
                np.testing.assert_array_equal(centroids[level, k].numpy(), centre)
    assert seen == set(range(FRAMES))
    # eval batches need no votes
    _, eval_data = manager.next_eval(0)
    assert "image" in eval_data


def test_vote_maps_in_memory_bounds_the_views_kept_and_reuses_them(dataset, tmp_path, monkeypatch):
    manager = setup_manager(dataset, tmp_path / "cache", vote_maps_in_memory=2)
    first = {index: manager.vote_batch(index) for index in range(FRAMES)}
    assert list(manager._in_memory) == [FRAMES - 2, FRAMES - 1]  # least recently used views were dropped

    def no_disk_read(key):
        raise AssertionError("a view kept in memory was read from the cache again")

    monkeypatch.setattr(manager._vote_cache, "load", no_disk_read)
    again = manager.vote_batch(FRAMES - 2)
    assert torch.equal(again["vote_labels"], first[FRAMES - 2]["vote_labels"])
    monkeypatch.undo()
    # another resolution is derived again, and an evicted view is read back identically
    assert manager.vote_batch(FRAMES - 2, HEIGHT // 2, WIDTH // 2)["vote_labels"].shape == (2, HEIGHT // 2, WIDTH // 2)
    assert torch.equal(manager.vote_batch(0)["vote_labels"], first[0]["vote_labels"])
    assert len(manager._in_memory) == 2


def test_cache_vote_maps_gpu_keeps_them_on_the_training_device(dataset, tmp_path):
    """cache_vote_maps "gpu": the kept vote tensors are on the datamanager's device (so a vote step copies
    nothing), with the values "cpu" keeps in host memory. (A "meta" device stands in for CUDA here.)"""
    on_host = setup_manager(dataset, tmp_path / "cache")
    on_device = setup_manager(dataset, tmp_path / "cache", cache_vote_maps="gpu")
    on_device.device = torch.device("meta")
    for index in range(FRAMES):
        kept, expected = on_device.kept_vote_batch(index), on_host.kept_vote_batch(index)
        assert set(kept) == set(expected) == {"vote_labels", "vote_centroids", "vote_pixels"}
        for name, tensor in kept.items():
            assert tensor.device.type == "meta" and expected[name].device.type == "cpu"
            assert tensor.dtype == expected[name].dtype and tensor.shape == expected[name].shape
        # kept: a second request hands out the same device tensors, not new copies
        assert on_device.kept_vote_batch(index)["vote_labels"] is kept["vote_labels"]


def test_place_vote_batch_moves_or_keeps_the_tensors():
    tensors = {"vote_labels": torch.zeros(2, 3, 4, dtype=torch.int16), "vote_pixels": torch.arange(3).int()}
    assert place_vote_batch(tensors, torch.device("cpu"), "cpu") is tensors  # host memory, unpinned off CUDA
    moved = place_vote_batch(tensors, torch.device("meta"), "gpu")
    assert all(tensor.device.type == "meta" for tensor in moved.values())
    assert place_vote_batch(tensors, torch.device("cpu"), "gpu")["vote_labels"] is tensors["vote_labels"]


def test_first_step_prepares_every_view_in_the_background(dataset, tmp_path, monkeypatch):
    """From the first next_train, the views' vote batches are prepared by background threads (up to
    vote_maps_in_memory views in all); a later first visit takes the prepared batch, equal to one made on the spot."""
    manager = setup_manager(dataset, tmp_path / "cache", vote_maps_in_memory=FRAMES - 1)
    reference = setup_manager(dataset, tmp_path / "cache")
    camera, _ = manager.next_train(0)
    assert camera.metadata is not None
    visited = int(camera.metadata["cam_idx"])
    assert manager._prefetch is not None
    assert len(manager._prefetch) == FRAMES - 2 and visited not in manager._prefetch
    prepared = dict(manager._prefetch)
    made_here = []
    original = manager._vote_batch_tensors
    monkeypatch.setattr(manager, "_vote_batch_tensors", lambda *args: made_here.append(args) or original(*args))
    for index in prepared:
        batch = manager.vote_batch(index)
        assert prepared[index].done() and index not in manager._prefetch
        expected = reference.vote_batch(index)
        for name in expected:
            torch.testing.assert_close(batch[name], expected[name], rtol=0, atol=0, equal_nan=True)
    assert made_here == []  # none was made again


def test_downscaled_images_get_downscaled_vote_maps(dataset, tmp_path):
    manager = setup_manager(dataset, tmp_path / "cache", downscale=2, border_masks="vote")
    assert "images_2" in str(manager.train_dataset.image_filenames[0])
    for step in range(FRAMES):
        camera, data = manager.next_train(step)
        index = int(camera.metadata["cam_idx"])
        labels, centroids = data["vote_labels"], data["vote_centroids"]
        assert labels.shape == (2, *data["image"].shape[:2]) == (2, HEIGHT // 2, WIDTH // 2)
        instance, part = frame_labels(frame_number(manager, index))
        # nearest-neighbour: output pixel j samples the full-resolution pixel 2j + 1
        assert np.array_equal(labels[0].numpy(), instance[1::2, 1::2])  # border mask kept (drop off)
        assert np.array_equal(labels[1].numpy(), renumbered_parts(part)[1::2, 1::2])
        for k, centre in expected_centroids(instance).items():
            np.testing.assert_allclose(centroids[0, k].numpy(), (centre + 0.5) / 2 - 0.5, atol=1e-6)


def test_undistorted_images_get_warped_vote_maps(tmp_path):
    data = make_dataset(tmp_path / "distorted", k1=-0.35)
    manager = setup_manager(data, tmp_path / "cache")
    camera, batch = manager.next_train(0)
    labels, centroids = batch["vote_labels"], batch["vote_centroids"]
    assert labels.shape == (2, *batch["image"].shape[:2])
    assert batch["image"].shape[:2] != (HEIGHT, WIDTH)  # nerfstudio cropped the undistorted image
    # nerfstudio warped the image bilinearly; where its red channel is a clean id code, the
    # warped labels must carry that id
    red = batch["image"][..., 0].numpy().astype(np.int64)
    decoded = np.rint(red / INSTANCE_CODE).astype(np.int64)
    clean = (np.abs(red - decoded * INSTANCE_CODE) <= 2) & (decoded != BORDER_ID)
    agreement = (labels[0].numpy()[clean] == decoded[clean]).mean()
    # (resizing without the warp agrees on only ~95% of these pixels)
    assert clean.sum() > 0.8 * clean.size and agreement > 0.98
    for level in range(2):
        level_labels = labels[level].numpy()
        assert level_labels.max() >= 1
        for k, centre in expected_centroids(level_labels).items():
            np.testing.assert_array_equal(centroids[level, k].numpy(), centre)


def test_view_without_masks_and_unsafe_cache_dir(tmp_path):
    data = make_dataset(tmp_path / "empty")
    for folder in ("instances", "parts"):
        for path in (data / folder).iterdir():
            Image.fromarray(np.zeros((HEIGHT, WIDTH), np.uint16)).save(path)
    manager = setup_manager(data, tmp_path / "cache")
    _, batch = manager.next_train(0)
    assert not batch["vote_labels"].any() and batch["vote_centroids"].shape == (2, 1, 2)
    assert batch["vote_pixels"].shape == (0,)
    with pytest.raises(ValueError, match="inside the dataset"):
        setup_manager(data, data / "votesplat_cache")


def test_masks_cli_precomputes_the_cache_training_reuses(dataset, tmp_path):
    result = masks_main(MasksConfig(data=dataset, output_dir=tmp_path / "outputs", preview=2))
    assert len(result["keys"]) == FRAMES
    previews = result["previews"]
    assert len(previews) == 2
    picture = np.asarray(Image.open(previews[0]))
    assert picture.shape == (HEIGHT, 2 * WIDTH + 3, 3)
    entries = sorted(Path(result["entry_dir"]).glob("*.votes.npz"))
    assert len(entries) == FRAMES
    stamps = [p.stat().st_mtime_ns for p in entries]

    cache_dir = default_cache_dir(dataset, tmp_path / "outputs")
    assert Path(result["entry_dir"]).parent == cache_dir
    manager = setup_manager(dataset, cache_dir)
    manager.next_train(0)
    assert [p.stat().st_mtime_ns for p in sorted(Path(result["entry_dir"]).glob("*.votes.npz"))] == stamps


def test_mask_source_choice_and_sam_checkpoint_hint(dataset, tmp_path):
    auto = VoteDataManagerConfig(data=dataset)
    assert auto.resolved_mask_source() == "dataset" and auto.resolved_levels() == ("instance", "part")

    capture = tmp_path / "capture"  # a real capture: no label paths in transforms.json
    capture.mkdir()
    meta = json.loads((dataset / "transforms.json").read_text())
    for frame in meta["frames"]:
        del frame["instance_mask_path"], frame["part_mask_path"]
    (capture / "transforms.json").write_text(json.dumps(meta))
    config = VoteDataManagerConfig(data=capture)
    assert config.resolved_mask_source() == "sam" and config.resolved_levels() == ("default", "s", "m", "l")
    with pytest.raises(ValueError) as error:
        config.make_mask_source()
    message = str(error.value)
    assert "no instance_mask_path" in message and "--pipeline.datamanager.sam-checkpoint" in message
    assert "sam_vit_h_4b8939.pth" in message and "\n" not in message
    with pytest.raises(ValueError, match="mask-folder"):
        VoteDataManagerConfig(data=capture, mask_source="folder").make_mask_source()
