"""votesplat query / click / query-eval on the bundled demo scene, with the session's trained run."""

from __future__ import annotations

import colorsys
import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

import votesplat_ns
from votesplat_ns.cli.main import main
from votesplat_ns.cli.query_cli import Query, QueryEval
from votesplat_ns.core.clustering import cluster_levels
from votesplat_ns.core.ply_io import read_gaussian_ply
from votesplat_ns.core.semantics import InstanceFeatures
from votesplat_ns.eval.lerf_ovs import category_masks, load_scene_labels, mask_iou
from votesplat_ns.eval.synthetic.labels import write_scene_labels
from votesplat_ns.ns.query import evaluate_queries, run_click, run_query
from votesplat_ns.ns.run_instances import InstanceSettings, run_instances
from votesplat_ns.ns.selection import QueryScene, instances_of_level

DEMO_SCENE = Path(votesplat_ns.__file__).resolve().parent / "data" / "demo"
TRANSFORMS = json.loads((DEMO_SCENE / "transforms.json").read_text())
SMALL_CLIP = "ViT-S-32-alt"  # the smallest open_clip architecture that builds offline


class ColourNameEncoder:
    """Deterministic stand-in for CLIP whose features mean something on the demo scene.

    Image feature: histogram of the crop's pixels over colour names (HSV rules; exact black is
    the crop's masked-out padding and is skipped). Text feature: the colour words of the text,
    one-hot; a text without colour words (LERF's negatives) is the uniform vector.
    """

    NAMES = ("black", "grey", "white", "red", "brown", "yellow", "green", "blue", "purple")
    config = {"kind": "colour_name_test", "names": list(NAMES)}

    def encode_images(self, crops):
        rows = []
        for crop in crops:
            pixels = crop.reshape(-1, 3)
            pixels = pixels[pixels.any(axis=1)].astype(np.float64) / 255.0
            histogram = torch.zeros(len(self.NAMES))
            for r, g, b in pixels:
                histogram[self.NAMES.index(self.colour_name(r, g, b))] += 1.0
            rows.append(histogram)
        return F.normalize(torch.stack(rows), dim=-1)

    @staticmethod
    def colour_name(r: float, g: float, b: float) -> str:
        hue, saturation, value = colorsys.rgb_to_hsv(r, g, b)
        if value < 0.16:
            return "black"
        if saturation < 0.25:
            return "white" if value > 0.75 else "grey"
        if hue < 0.04 or hue >= 0.92:
            return "red"
        if hue < 0.11:
            return "brown"
        if hue < 0.2:
            return "yellow"
        if hue < 0.45:
            return "green"
        if hue < 0.7:
            return "blue"
        return "purple"

    def encode_text(self, texts):
        rows = []
        for text in texts:
            words = [word for word in text.lower().split() if word in self.NAMES]
            vector = torch.zeros(len(self.NAMES))
            for word in words:
                vector[self.NAMES.index(word)] = 1.0
            if not words:
                vector[:] = 1.0
            rows.append(vector)
        return F.normalize(torch.stack(rows), dim=-1)


@pytest.fixture(scope="module")
def demo_scene(trained_demo) -> QueryScene:
    return QueryScene.from_config(trained_demo)


def ground_truth_labels(camera) -> np.ndarray:
    """The demo scene's instance label image (0 = background) of a run's camera."""
    frame = next(f for f in TRANSFORMS["frames"] if Path(f["file_path"]).name == Path(camera.name).name)
    return np.asarray(Image.open(DEMO_SCENE / frame["instance_mask_path"])).astype(np.int64)


def project_pixels(means: np.ndarray, camera) -> np.ndarray:
    """Pixel (column, row) [N, 2] of points, -1 where behind the camera or outside the image."""
    viewmat = camera.viewmat.double().numpy()
    K = camera.K.double().numpy()
    points = means @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = points[:, 2]
    u = K[0, 0] * points[:, 0] / z + K[0, 2]
    v = K[1, 1] * points[:, 1] / z + K[1, 2]
    pixels = np.stack([np.floor(u), np.floor(v)], axis=1).astype(np.int64)
    inside = (
        (z > 0)
        & (pixels[:, 0] >= 0)
        & (pixels[:, 1] >= 0)
        & (pixels[:, 0] < camera.width)
        & (pixels[:, 1] < camera.height)
    )
    pixels[~inside] = -1
    return pixels


def fraction_projecting_into(means: np.ndarray, camera, mask: np.ndarray) -> float:
    pixels = project_pixels(means, camera)
    seen = pixels[:, 0] >= 0
    hits = np.zeros(len(means), dtype=bool)
    hits[seen] = mask[pixels[seen, 1], pixels[seen, 0]]
    return float(hits.mean())


def interior_pixel(mask: np.ndarray):
    """The pixel of ``mask`` farthest from its outline (its 'centre', inside even for a ring)."""
    distance = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 5)
    row, column = np.unravel_index(np.argmax(distance), distance.shape)
    return int(column), int(row), float(distance[row, column])


def test_click_selects_the_ground_truth_object(demo_scene, trained_demo, tmp_path, capsys):
    clicks = []  # (view, ground-truth id, x, y) where the id render is confident at the object's centre
    for view in (0, 19):
        camera = demo_scene.train_camera(view)
        labels = ground_truth_labels(camera)
        for object_id in (entry["id"] for entry in TRANSFORMS["instances"]):
            column, row, depth = interior_pixel(labels == object_id)
            # min_weight 0.5 of the id render: a non-negative id means one instance makes up most of the pixel
            if depth >= 3 and demo_scene.id_map(camera)[row, column] >= 0:
                clicks.append((view, object_id, column, row))
    assert len(clicks) >= 6, f"the trained model's instance render is confident at too few object centres: {clicks}"

    correct = 0
    for view, object_id, column, row in clicks:
        instance_id = demo_scene.instance_at(view, column + 0.5, row + 0.5)
        members = demo_scene.level.ids == instance_id
        camera = demo_scene.train_camera(view)
        inside = fraction_projecting_into(
            demo_scene.params.means[members], camera, ground_truth_labels(camera) == object_id
        )
        correct += inside > 0.7
    assert correct >= 0.8 * len(clicks), f"{correct} of {len(clicks)} clicks selected the clicked object"

    # The console script end to end: isolate, then remove, the first clicked object.
    view, object_id, column, row = clicks[0]
    common = ["--load-config", str(trained_demo), "--view", str(view), "--x", str(column + 0.5), "--y", str(row + 0.5)]
    main(["click", *common, "--isolate", "--output-dir", str(tmp_path / "isolate")])
    run_click(demo_scene, view, column + 0.5, row + 0.5, tmp_path / "remove", mode="remove")
    isolated = json.loads((tmp_path / "isolate" / "click.json").read_text())
    removed = json.loads((tmp_path / "remove" / "click.json").read_text())
    assert isolated["instance_id"] == removed["instance_id"]
    assert isolated["mode"] == "isolate" and removed["mode"] == "remove"
    assert f"instance {isolated['instance_id']}" in capsys.readouterr().out
    alone = read_gaussian_ply(tmp_path / "isolate" / isolated["ply"])
    rest = read_gaussian_ply(tmp_path / "remove" / removed["ply"])
    assert len(alone["means"]) == isolated["ply_count"] > 0
    assert len(rest["means"]) == removed["ply_count"] > 0
    # The two files split the exportable Gaussians: no instance Gaussian remains in the removal.
    whole = {tuple(m) for m in rest["means"].tolist()}
    assert not any(tuple(m) in whole for m in alone["means"].tolist())
    render = np.asarray(Image.open(tmp_path / "isolate" / isolated["render"]))
    camera = demo_scene.train_camera(view)
    assert render.shape == (camera.height, camera.width, 4)
    assert render[row, column, 3] > 127, "the isolated object is drawn where it was clicked"


def test_query_end_to_end_with_random_clip_weights(trained_demo, demo_scene, tmp_path, capsys):
    cache_dir = tmp_path / "cache"
    out = tmp_path / "query"
    first = main(
        [
            "query",
            "--load-config",
            str(trained_demo),
            "purple ball",
            "--clip-random-init",
            "--clip-model",
            SMALL_CLIP,
            "--feature-views",
            "2",
            "--features-cache",
            str(cache_dir),
            "--views",
            "0",
            "3",
            "--output-dir",
            str(out),
            "--top-k",
            "3",
        ]
    )
    printed = capsys.readouterr().out
    assert "features computed" in printed
    rows = [line.split() for line in printed.splitlines() if line.split()[:1] in (["1"], ["2"], ["3"])]
    assert len(rows) == 3
    ranked = first["ranking"]
    assert [int(row[1]) for row in rows] == [entry["id"] for entry in ranked[:3]]
    assert [entry["relevancy"] for entry in ranked] == sorted((entry["relevancy"] for entry in ranked), reverse=True)
    assert all(int(row[3]) == demo_scene.level.counts[int(row[1])] for row in rows)
    assert first["selected"] == [ranked[0]["id"]]
    for name in ("mask_0000.png", "render_0000.png", "mask_0003.png", "render_0003.png", "ranking.json"):
        assert (out / name).is_file(), name
    # The mask is the selection's silhouette (accumulated opacity > 0.7 of its Gaussians alone).
    _, alpha = demo_scene.render(demo_scene.selection_mask(first["selected"]), demo_scene.train_camera(3))
    mask = np.asarray(Image.open(out / "mask_0003.png"))
    assert set(np.unique(mask)) <= {0, 255}
    np.testing.assert_array_equal(mask == 255, alpha > 0.7)
    assert np.asarray(Image.open(out / "render_0003.png")).shape == (128, 128, 4)
    assert json.loads((out / "ranking.json").read_text())["selected"] == first["selected"]

    cache_file = next(cache_dir.glob("instance_features_*.npz"))
    stamp = cache_file.stat().st_mtime_ns
    # Later calls in-process on the same run (loading it again through the CLI costs seconds).
    again = Query(
        load_config=trained_demo,
        text="purple ball",
        clip_random_init=True,
        clip_model=SMALL_CLIP,
        feature_views=2,
        features_cache=cache_dir,
        views=(),
        output_dir=tmp_path / "again",
    )
    second = again.run(scene=demo_scene)
    assert "features from cache" in capsys.readouterr().out
    assert second["features_from_cache"] and second["ranking"] == first["ranking"]
    assert cache_file.stat().st_mtime_ns == stamp

    third = dataclasses.replace(again, clip_model="ViT-S-16-alt").run(scene=demo_scene)
    assert "Rebuilding instance features" in capsys.readouterr().out
    assert not third["features_from_cache"]
    assert InstanceFeatures.load(cache_file).config["encoder"]["model_name"] == "ViT-S-16-alt"


def test_instances_from_an_export_are_the_ones_clustered_here(demo_scene, tmp_path):
    # votesplat export clusters every level; --instances reads its instance_ids.npz back.
    params = demo_scene.params
    saved = cluster_levels(params.means, params.vote_offsets, params.vote_support, params.level_names)
    saved.save(tmp_path)
    never = lambda: pytest.fail("--instances must not compute the run's instances")  # noqa: E731
    exported, source = instances_of_level(params, None, tmp_path, never)
    np.testing.assert_array_equal(exported.ids, saved.levels[0].ids)
    assert source == f"export {tmp_path}"
    part, _ = instances_of_level(params, "1", tmp_path, never)
    assert part.name == "part"
    fewer = dataclasses.replace(params, means=params.means[:-1])
    with pytest.raises(ValueError, match="export again from this checkpoint or drop --instances"):
        instances_of_level(fewer, None, tmp_path, never)
    with pytest.raises(ValueError, match="unknown vote level 'shelf'"):
        instances_of_level(params, "shelf", None, never)
    # without --instances: the run's instances (the record every command reads), the asked level of them
    run = run_instances(params, tmp_path / "run", InstanceSettings.make(mask_check=False))
    chosen, source = instances_of_level(params, "part", None, lambda: run)
    assert source == "run" and chosen is run.level("part")


def test_labels_from_ground_truth_masks(tmp_path, capsys):
    main(["write-labels", "--scene", str(DEMO_SCENE), "--output-dir", str(tmp_path)])
    assert f"Wrote 4 label files to {tmp_path}" in capsys.readouterr().out
    paths = sorted(tmp_path.glob("*.json"))
    eval_frames = TRANSFORMS["votesplat_synthetic"]["eval_frames"]
    assert [path.name for path in paths] == [Path(name).stem + ".json" for name in eval_frames]
    frames = load_scene_labels(tmp_path)
    names = {entry["id"]: entry["name"] for entry in TRANSFORMS["instances"]}
    for frame in frames:
        labels = np.asarray(Image.open(DEMO_SCENE / "instances" / frame.name)).astype(np.int64)
        masks = category_masks(frame)
        assert set(masks) == {names[i] for i in np.unique(labels) if i in names}
        for object_id, name in names.items():
            if name in masks:
                assert mask_iou(masks[name], labels == object_id) > 0.9, (frame.name, name)


def test_query_eval_selects_the_named_objects(demo_scene, trained_demo, tmp_path, capsys):
    labels = tmp_path / "labels"
    write_scene_labels(DEMO_SCENE, labels)
    command = QueryEval(
        load_config=trained_demo,
        labels=labels,
        feature_views=5,
        features_cache=tmp_path,
        output=tmp_path / "scores.json",
    )
    summary = command.run(encoder=ColourNameEncoder(), scene=demo_scene)
    printed = capsys.readouterr().out
    assert f"mIoU {summary['mIoU']:.4f}" in printed
    queries = summary["queries"]
    assert len(queries) >= 12  # 4 held-out frames with about 5 objects each
    assert summary["mAcc@0.25"] >= 0.75, queries
    assert json.loads((tmp_path / "scores.json").read_text())["mIoU"] == summary["mIoU"]

    # The right object: the selected Gaussians land in that category's ground-truth mask more
    # than in any other category's (measured on the points, so over-large splats do not blur it).
    right, total = 0, 0
    for frame in load_scene_labels(labels):
        camera = demo_scene.camera_for_image(frame.name)
        masks = category_masks(frame)
        for category in masks:
            members = demo_scene.selection_mask(summary["selections"][category])
            share = {
                other: fraction_projecting_into(demo_scene.params.means[members], camera, mask)
                for other, mask in masks.items()
            }
            right += max(share, key=share.get) == category
            total += 1
    assert right >= 0.8 * total, f"{right} of {total} queries selected the named object"


def test_bad_input_is_one_clear_line(demo_scene, trained_demo, tmp_path, capsys):
    run = ["query", "--load-config", str(trained_demo), "red mug"]
    with pytest.raises(SystemExit) as exit_info:
        main([*run, "--clip-checkpoint", str(tmp_path / "missing.bin")])
    assert exit_info.value.code == 1
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and "CLIP checkpoint not found" in error and "missing.bin" in error

    with pytest.raises(SystemExit):
        main(run)
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1
    assert "open_clip_pytorch_model.bin" in error and "laion/CLIP-ViT-B-16-laion2B-s34B-b88K" in error

    with pytest.raises(SystemExit):
        main(["query", "--load-config", str(trained_demo), "  ", "--clip-random-init"])
    assert "text query is empty" in capsys.readouterr().err

    views = len(demo_scene.train_views)
    with pytest.raises(ValueError, match=f"view {views} is out of range: this run has {views} training views"):
        run_click(demo_scene, views, 1.0, 1.0, tmp_path / "out")
    with pytest.raises(ValueError, match="out of range"):
        run_query(demo_scene, "ball", ColourNameEncoder(), tmp_path / "q", views=[-1])
    with pytest.raises(
        ValueError,
        match=r"--x 200.0 --y 5.0 is outside training view 0, which is 128x128 pixels; give --x in \[0, 128\)",
    ):
        run_click(demo_scene, 0, 200.0, 5.0, tmp_path / "out")
    camera = demo_scene.train_camera(0)
    background = np.argwhere((demo_scene.id_map(camera) < 0) & (ground_truth_labels(camera) == 0))
    row, column = background[0]
    with pytest.raises(ValueError, match="no instance under pixel"):
        run_click(demo_scene, 0, column + 0.5, row + 0.5, tmp_path / "out")
    assert not (tmp_path / "out").exists(), "a failed click writes nothing"

    with pytest.raises(ValueError, match="frame 'nope.png' is not in"):
        write_scene_labels(DEMO_SCENE, tmp_path / "labels", frames=["nope.png"])
    labels = tmp_path / "labels"
    write_scene_labels(DEMO_SCENE, labels, frames=["frame_00001.png"])
    frames = load_scene_labels(labels)
    renamed = [dataclasses.replace(frames[0], name="frame_00099.png")]
    with pytest.raises(ValueError, match="no training or evaluation image named like 'frame_00099.png'"):
        evaluate_queries(demo_scene, renamed, ColourNameEncoder(), cache_path=tmp_path / "features.npz")
