"""The mask check's glue (votesplat_ns/ns/mask_views.py): training views and masks from a run's
vote datamanager, and the check with either kind of evidence, on two objects that the vote
clustering left in one cluster."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from nerfstudio.cameras.cameras import Cameras

from votesplat_ns.core.instances import render_instance_ids
from votesplat_ns.core.mask_consensus import drawn_masks, seen_mask_table, seen_pixels
from votesplat_ns.core.rasterize_torch import rasterize_torch
from votesplat_ns.core.scene import TrainedScene
from votesplat_ns.ns.mask_views import mask_check, mask_tables, training_mask_views
from votesplat_ns.ns.run import camera_view

WIDTH, HEIGHT, VIEWS = 64, 48, 6


def look_at(position, target=(0.0, 0.0, 0.0)):
    """Camera-to-world [3, 4] in nerfstudio's convention (the camera looks down its -z)."""
    position = np.asarray(position, dtype=np.float64)
    back = position - np.asarray(target)
    back /= np.linalg.norm(back)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    return np.stack([right, up, back, position], axis=1)


def two_objects():
    """A large blob and a small one resting against it (labels 1 and 2), and a ring of cameras."""
    rng = np.random.default_rng(0)
    large = rng.normal([-0.1, 0, 0], 0.12, size=(800, 3))
    small = rng.normal([0.3, 0, 0], 0.06, size=(200, 3))
    means = np.concatenate([large, small]).astype(np.float32)
    truth = np.repeat([1, 2], [800, 200])
    n = means.shape[0]
    params = {
        "means": means,
        "scales": np.full((n, 3), np.log(0.05), dtype=np.float32),
        "quats": np.tile(np.array([1.0, 0, 0, 0], dtype=np.float32), (n, 1)),
        "opacities": np.full((n, 1), 4.0, dtype=np.float32),
        "features_dc": np.zeros((n, 3), dtype=np.float32),
        "vote_offsets": np.zeros((n, 1, 3), dtype=np.float32),
        "vote_support": np.ones((n, 1), dtype=np.float32),
    }
    scene = TrainedScene.from_params(params, level_names=("instance",))
    angles = np.linspace(0, 2 * np.pi, VIEWS, endpoint=False)
    c2w = np.stack([look_at([2.5 * np.sin(a), -2.5 * np.cos(a), 0.8]) for a in angles])
    cameras = Cameras(
        camera_to_worlds=torch.tensor(c2w, dtype=torch.float32),
        fx=60.0,
        fy=60.0,
        cx=WIDTH / 2,
        cy=HEIGHT / 2,
        width=WIDTH,
        height=HEIGHT,
    )
    return scene, truth, cameras


def pipeline_with_true_masks(scene, truth, cameras):
    """A stand-in for a loaded run's pipeline whose datamanager serves the true masks."""
    means, quats, scales, opacities = scene.gaussians(scene.finite())[:4]
    labels = []
    for i in range(VIEWS):
        view = camera_view(cameras, i)
        ids = render_instance_ids(
            rasterize_torch, means, quats, scales, opacities, truth - 1, view.viewmat, view.K, WIDTH, HEIGHT
        )
        labels.append((ids + 1).numpy())

    def vote_maps_for_train_view(index, height, width):
        assert (height, width) == (HEIGHT, WIDTH)
        return SimpleNamespace(labels=labels[index][None])

    datamanager = SimpleNamespace(
        vote_levels=["instance"],
        train_dataset=SimpleNamespace(cameras=cameras),
        vote_maps_for_train_view=vote_maps_for_train_view,
    )
    return SimpleNamespace(datamanager=datamanager), labels


def test_training_mask_views_reads_the_datamanagers_masks():
    scene, truth, cameras = two_objects()
    pipeline, labels = pipeline_with_true_masks(scene, truth, cameras)
    views, masks = training_mask_views(pipeline, ["instance"], max_views=3)
    assert [v.width for v in views] == [WIDTH] * 3
    assert len(masks["instance"]) == 3 and np.array_equal(masks["instance"][0], labels[0])
    assert {1, 2} <= set(np.unique(labels[0]).tolist())  # both objects are in the masks
    with pytest.raises(ValueError, match="no masks for"):
        training_mask_views(pipeline, ["part"])


@pytest.mark.parametrize("evidence", ["centre", "blend"])
def test_mask_tables_are_built_one_view_at_a_time(evidence):
    """Each view's masks are read as that view is rendered (never every view's at once), and the tables equal
    those made from every view's masks and renders together."""
    scene, truth, cameras = two_objects()
    pipeline, _ = pipeline_with_true_masks(scene, truth, cameras)
    scene.means[5] = np.nan  # never seen
    events = []
    read_masks = pipeline.datamanager.vote_maps_for_train_view

    def recording_read(index, height, width):
        events.append(("masks", index))
        return read_masks(index, height, width)

    def recording_rasterize(*args, **kwargs):
        events.append(("render",))
        return rasterize_torch(*args, **kwargs)

    pipeline.datamanager.vote_maps_for_train_view = recording_read
    tables = mask_tables(pipeline, scene, recording_rasterize, max_views=VIEWS, evidence=evidence)
    table = tables["instance"]
    assert table.dtype == np.int16 and table.shape == (VIEWS, len(truth))
    reads = [i for i, event in enumerate(events) if event[0] == "masks"]
    assert [events[i][1] for i in reads] == list(range(VIEWS))
    assert all(events[i + 1] == ("render",) for i in reads)  # each view rendered before the next one's masks

    pipeline.datamanager.vote_maps_for_train_view = read_masks
    views, masks = training_mask_views(pipeline, ["instance"], max_views=VIEWS)
    finite = scene.finite()
    gaussians = scene.gaussians(finite)[:4]
    expected = np.full(table.shape, -1, dtype=np.int32)
    if evidence == "centre":
        pixels = []
        for view in views:
            seen = np.full(len(truth), -1, dtype=np.int64)
            seen[finite] = seen_pixels(rasterize_torch, *gaussians, view)
            pixels.append(seen)
        expected = seen_mask_table(pixels, masks["instance"])
    else:
        for v, view in enumerate(views):
            expected[v, finite] = drawn_masks(rasterize_torch, *gaussians, view, masks["instance"][v])
    np.testing.assert_array_equal(table, expected)
    assert (table[:, 5] == -1).all() and (table >= 1).any()


def test_mask_tables_widen_for_more_masks_than_int16_holds():
    scene, truth, cameras = two_objects()
    pipeline, labels = pipeline_with_true_masks(scene, truth, cameras)
    labels[2][labels[2] == 2] = 40000
    table = mask_tables(pipeline, scene, rasterize_torch, max_views=VIEWS)["instance"]
    assert table.dtype == np.int32 and table.max() == 40000


def test_mask_check_splits_a_small_object_off_the_large_one_it_rests_against():
    scene, truth, cameras = two_objects()
    pipeline, _ = pipeline_with_true_masks(scene, truth, cameras)
    merged = np.zeros(len(truth), dtype=np.int64)  # the vote clustering left both in one cluster
    # the split alone (the bisect rule, which also hands undecided members to a side, off)
    check = dict(max_views=VIEWS, evidence="blend", bisect=False)
    ids, stats = mask_check(pipeline, scene, rasterize_torch, grow=False, **check)(0, "instance", merged)
    assert stats["num_clusters"] == 2
    large = np.bincount(ids[truth == 1]).argmax()
    assert (ids[truth == 1] == large).mean() > 0.97
    split_off = (ids[truth == 2] != large).mean()
    assert split_off > 0.15  # the small object's visible surface leaves the large one's cluster
    # with grow (the default), the members no view decided follow the nearest decided ones
    grown, _ = mask_check(pipeline, scene, rasterize_torch, grow=True, **check)(0, "instance", merged)
    large = np.bincount(grown[truth == 1]).argmax()
    assert (grown[truth == 1] == large).mean() > 0.97
    assert (grown[truth == 2] != large).mean() > max(0.8, split_off)
    # the defaults (grow and bisect) keep the two apart as well
    default, _ = mask_check(pipeline, scene, rasterize_torch, max_views=VIEWS, evidence="blend")(0, "instance", merged)
    large = np.bincount(default[truth == 1]).argmax()
    assert (default[truth == 1] == large).mean() > 0.97 and (default[truth == 2] != large).mean() > 0.8


@pytest.mark.parametrize("evidence", ["centre", "blend"])
def test_mask_check_keeps_one_object_whole(evidence):
    scene, truth, cameras = two_objects()
    pipeline, labels = pipeline_with_true_masks(scene, truth, cameras)
    for view_labels in labels:  # the masks see one object where the two blobs are
        view_labels[view_labels == 2] = 1
    ids, stats = mask_check(pipeline, scene, rasterize_torch, max_views=VIEWS, evidence=evidence, grow=True)(
        0, "instance", np.zeros(len(truth), dtype=np.int64)
    )
    assert stats["num_clusters"] == 1 and (ids == 0).all()


def test_mask_check_names_an_unknown_evidence():
    scene, truth, cameras = two_objects()
    pipeline, _ = pipeline_with_true_masks(scene, truth, cameras)
    with pytest.raises(ValueError, match="evidence must be"):
        mask_check(pipeline, scene, rasterize_torch, max_views=2, evidence="depth")


def test_mask_check_gives_an_objects_hidden_core_to_it():
    scene, truth, cameras = two_objects()
    pipeline, _ = pipeline_with_true_masks(scene, truth, cameras)
    core = np.linalg.norm(scene.means - np.array([-0.1, 0, 0]), axis=1) < 0.08
    assert core.sum() > 20
    ids = truth - 1
    ids[core] = -1  # never voted: hidden behind the blob's surface in every view
    out, stats = mask_check(pipeline, scene, rasterize_torch, max_views=VIEWS)(0, "instance", ids)
    large = np.bincount(out[truth == 1][~core[truth == 1]]).argmax()
    assert (out[core] == large).mean() > 0.9
    assert stats["objects"]["hidden"]["hidden_taken"] >= 0.9 * core.sum()
    assert stats["confidence"].shape == (stats["num_clusters"],)
    kept, _ = mask_check(pipeline, scene, rasterize_torch, max_views=VIEWS, hidden=False)(0, "instance", ids)
    assert (kept[core] == -1).mean() > 0.9
