"""Tests for votesplat_ns.ns.viewer (and its viewer_render, viewer_state): overlay, click/text selection, isolate/hide, votes picture, export.

Model-free scenes (random Gaussians with known instance ids) rendered by the project's torch
rasteriser, plus one test of the nerfstudio glue on a small real VoteSplatModel.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from votesplat_ns.core.cameras import PinholeView
from votesplat_ns.core.instances import InstanceSet, LevelInstances, instance_colors, render_instance_ids
from votesplat_ns.core.ply_io import read_gaussian_ply
from votesplat_ns.core.scene import Gaussians
from votesplat_ns.ns.rasterizer import rasterize
from votesplat_ns.ns.viewer_render import (
    DISPLAY_ALL,
    DISPLAY_HIDE,
    DISPLAY_ISOLATE,
    OUTPUT_INSTANCES,
    OUTPUT_OVERLAY,
    OUTPUT_VOTES,
    OVERLAY_OPACITY,
    SELECTED_OPACITY,
    UNSELECTED_OPACITY,
    VIEWER_OUTPUTS,
    VOTE_BACKGROUND_GREY,
    ViewerScene,
    overlay_instances,
    render_rgb,
    render_vote_picture,
    screen_to_pixel,
    vote_colours,
)
from votesplat_ns.ns.viewer_state import InstanceViewerState

WIDTH, HEIGHT = 48, 40
GROUP_CENTRES = ((-0.9, 0.0, 4.0), (0.0, 0.1, 3.5), (0.9, -0.1, 4.2))
GROUP_COLOURS = ((0.9, 0.1, 0.1), (0.1, 0.85, 0.15), (0.1, 0.15, 0.9))
GROUP_SIZE = 40
NUM_BACKGROUND = 60


def look_at(eye, target=(0.0, 0.0, 4.0)) -> torch.Tensor:
    """OpenCV world-to-camera matrix from eye towards target (world y down, as the camera at the origin)."""
    eye, target = torch.tensor(eye, dtype=torch.float32), torch.tensor(target, dtype=torch.float32)
    forward = F.normalize(target - eye, dim=0)
    right = F.normalize(torch.linalg.cross(torch.tensor([0.0, -1.0, 0.0]), forward), dim=0)
    down = torch.linalg.cross(forward, right)
    rotation = torch.stack([right, down, forward])
    viewmat = torch.eye(4)
    viewmat[:3, :3] = rotation
    viewmat[:3, 3] = -rotation @ eye
    return viewmat


def make_view(eye=(0.0, 0.0, 0.0)) -> PinholeView:
    K = torch.tensor([[40.0, 0.0, WIDTH / 2], [0.0, 40.0, HEIGHT / 2], [0.0, 0.0, 1.0]])
    return PinholeView(viewmat=look_at(eye), K=K, width=WIDTH, height=HEIGHT)


def make_scene(seed: int = 0):
    """Three coloured blobs (instances 0, 1, 2) in front of a grey back wall (no instance).

    Each blob's votes point at its centre (the part level splits blob 0 into left/right halves);
    the wall has no vote support. Returns the scene and the per-Gaussian ids of both levels.
    """
    generator = torch.Generator().manual_seed(seed)
    means, colours, ids, part_ids, offsets = [], [], [], [], []
    for k, (centre, colour) in enumerate(zip(GROUP_CENTRES, GROUP_COLOURS)):
        centre = torch.tensor(centre)
        points = centre + 0.25 * torch.randn(GROUP_SIZE, 3, generator=generator)
        means.append(points)
        colours.append(torch.tensor(colour).expand(GROUP_SIZE, 3))
        ids.append(torch.full((GROUP_SIZE,), k))
        instance_votes = centre - points + 1e-3 * torch.randn(GROUP_SIZE, 3, generator=generator)
        if k == 0:
            left = points[:, 0] < centre[0]
            part_centre = torch.where(
                left[:, None], centre + torch.tensor([-0.2, 0, 0]), centre + torch.tensor([0.2, 0, 0])
            )
            part_ids.append(torch.where(left, 0, 1))
        else:
            part_centre = centre.expand(GROUP_SIZE, 3)
            part_ids.append(torch.full((GROUP_SIZE,), k + 1))
        part_votes = part_centre - points + 1e-3 * torch.randn(GROUP_SIZE, 3, generator=generator)
        offsets.append(torch.stack([instance_votes, part_votes], dim=1))
    wall = torch.stack(
        [
            torch.rand(NUM_BACKGROUND, generator=generator) * 8 - 4,
            torch.rand(NUM_BACKGROUND, generator=generator) * 7 - 3.5,
            torch.full((NUM_BACKGROUND,), 7.0),
        ],
        dim=1,
    )
    means.append(wall)
    colours.append(torch.full((NUM_BACKGROUND, 3), 0.5))
    ids.append(torch.full((NUM_BACKGROUND,), -1))
    part_ids.append(torch.full((NUM_BACKGROUND,), -1))
    offsets.append(torch.zeros(NUM_BACKGROUND, 2, 3))
    means = torch.cat(means)
    n = means.shape[0]
    support = torch.cat([torch.full((3 * GROUP_SIZE, 2), 5.0), torch.zeros(NUM_BACKGROUND, 2)])
    scales = torch.cat([torch.full((3 * GROUP_SIZE, 3), 0.12), torch.full((NUM_BACKGROUND, 3), 0.5)])
    gaussians = Gaussians(
        means=means,
        quats=F.normalize(torch.randn(n, 4, generator=generator), dim=-1),
        scales=scales * (0.8 + 0.4 * torch.rand(n, 3, generator=generator)),
        opacities=0.6 + 0.39 * torch.rand(n, generator=generator),
        colors=torch.cat(colours),
        sh_degree=None,
        vote_offsets=torch.cat(offsets),
        vote_support=support,
    )
    scene = ViewerScene(gaussians, background=torch.tensor([0.05, 0.05, 0.05]))
    return scene, torch.cat(ids).long(), torch.cat(part_ids).long()


def known_instances(scene: ViewerScene, ids: torch.Tensor, part_ids: torch.Tensor) -> InstanceSet:
    votes = (scene.gaussians.means + scene.gaussians.vote_offsets[:, 0]).numpy()
    levels = [
        LevelInstances.from_ids("instance", ids.numpy(), (ids >= 0).numpy(), scene.gaussians.means.numpy(), votes),
        LevelInstances.from_ids(
            "part", part_ids.numpy(), (part_ids >= 0).numpy(), scene.gaussians.means.numpy(), votes
        ),
    ]
    return InstanceSet(levels=levels, num_gaussians=scene.num_gaussians)


@pytest.fixture(scope="module")
def scene_and_ids():
    return make_scene()


@pytest.fixture(scope="module")
def front(scene_and_ids):
    """The front camera with the scene's rgb render and instance-id map (shared: renders cost time)."""
    scene, ids, _ = scene_and_ids
    view = make_view()
    return view, render_rgb(scene, view), direct_id_map(scene, view, ids)


@pytest.fixture()
def state(scene_and_ids):
    scene, ids, part_ids = scene_and_ids
    return InstanceViewerState(("instance", "part"), cluster_fn=lambda s, levels: known_instances(s, ids, part_ids))


def palette(instance_map: torch.Tensor) -> torch.Tensor:
    return torch.from_numpy(instance_colors(instance_map.numpy())).float() / 255.0


def direct_id_map(scene: ViewerScene, view: PinholeView, ids: torch.Tensor) -> torch.Tensor:
    return render_instance_ids(
        rasterize,
        scene.gaussians.means,
        scene.gaussians.quats,
        scene.gaussians.scales,
        scene.gaussians.opacities,
        ids,
        view.viewmat,
        view.K,
        view.width,
        view.height,
    )


# ------------------------------------------------------------------------------------------------
# overlay and "instances"


def test_overlay_and_instance_colours_follow_the_instance_id_render(scene_and_ids, front, state):
    scene, ids, _ = scene_and_ids
    view, base, id_map = front
    outputs = state.render_outputs(scene, view, base, wanted={OUTPUT_OVERLAY, OUTPUT_INSTANCES})
    assert set(outputs) == {OUTPUT_OVERLAY, OUTPUT_INSTANCES}

    assert set(torch.unique(id_map).tolist()) == {-1, 0, 1, 2}
    rgb, colours = base["rgb"], palette(id_map)
    assert len({tuple(c) for c in colours[id_map >= 0].tolist()}) == 3  # three distinct instance colours
    for k in (0, 1, 2):
        pixels = id_map == k
        expected = (1 - OVERLAY_OPACITY) * rgb[pixels] + OVERLAY_OPACITY * colours[pixels]
        torch.testing.assert_close(outputs[OUTPUT_OVERLAY][pixels], expected, rtol=0, atol=1e-7)
        assert torch.equal(outputs[OUTPUT_INSTANCES][pixels], colours[pixels])
    background = id_map < 0
    assert torch.equal(outputs[OUTPUT_OVERLAY][background], rgb[background])
    assert torch.equal(outputs[OUTPUT_INSTANCES][background], torch.zeros_like(rgb[background]))


def test_overlay_highlights_the_selected_instance(scene_and_ids, front, state):
    scene, ids, _ = scene_and_ids
    view, base, id_map = front
    state.select(1)
    overlay = state.render_outputs(scene, view, base, wanted={OUTPUT_OVERLAY})[OUTPUT_OVERLAY]
    colours = palette(id_map)
    for k, weight in ((1, SELECTED_OPACITY), (0, UNSELECTED_OPACITY), (2, UNSELECTED_OPACITY)):
        pixels = id_map == k
        torch.testing.assert_close(
            overlay[pixels], (1 - weight) * base["rgb"][pixels] + weight * colours[pixels], rtol=0, atol=1e-6
        )


def test_colours_are_the_same_from_another_view(scene_and_ids, front, state):
    scene, ids, _ = scene_and_ids
    seen = {}
    for view, id_map in ((front[0], front[2]), (make_view((1.5, -0.5, 0.5)), None)):
        instances = state.render_outputs(scene, view, front[1], wanted={OUTPUT_INSTANCES})[OUTPUT_INSTANCES]
        id_map = direct_id_map(scene, view, ids) if id_map is None else id_map
        for k in torch.unique(id_map[id_map >= 0]).tolist():
            colour = instances[id_map == k][0]
            assert torch.equal(instances[id_map == k], colour.expand(int((id_map == k).sum()), 3))
            seen.setdefault(k, []).append(colour)
    assert all(torch.equal(colours[0], c) for colours in seen.values() for c in colours) and len(seen) == 3


# ------------------------------------------------------------------------------------------------
# click selection


def test_click_selects_the_instance_under_the_cursor(scene_and_ids, front, state):
    scene, ids, _ = scene_and_ids
    view, base, id_map = front
    for k in (2, 0, 1, -1):
        rows, cols = torch.nonzero(id_map == k, as_tuple=True)
        middle = len(rows) // 2
        row, col = int(rows[middle]), int(cols[middle])
        state.request_click(((col + 0.5) / WIDTH, (row + 0.5) / HEIGHT))
        state.render_outputs(scene, view, base, wanted=set())  # the rgb output is on screen
        assert state.selected == (None if k < 0 else k), (k, row, col)
    assert state.cluster_calls == 1  # instances were computed on the first click, then reused


def test_click_and_screen_positions_are_checked(state):
    assert screen_to_pixel((1.0, 1.0), WIDTH, HEIGHT) < (WIDTH, HEIGHT)
    assert screen_to_pixel((0.5, 0.25), WIDTH, HEIGHT) == (WIDTH / 2, HEIGHT / 4)
    for bad in ((1.2, 0.5), (-0.1, 0.5), (math.nan, 0.1), (0.5,)):
        with pytest.raises(ValueError, match="screen_pos"):
            state.request_click(bad)


# ------------------------------------------------------------------------------------------------
# isolate / hide


def test_isolate_and_hide_change_which_gaussians_are_rendered(scene_and_ids, front, state):
    scene, ids, _ = scene_and_ids
    view, base, _ = front
    state.select(1)
    assert "rgb" not in state.render_outputs(scene, view, base, wanted=set())  # "show all": the model's rgb stays

    state.set_display(DISPLAY_ISOLATE)
    isolated = state.render_outputs(scene, view, base, wanted={OUTPUT_INSTANCES})
    only_one = render_rgb(scene.subset(ids == 1), view)
    assert torch.equal(isolated["rgb"], only_one["rgb"]) and torch.equal(
        isolated["accumulation"], only_one["accumulation"]
    )
    assert set(torch.unique(direct_id_map(scene.subset(ids == 1), view, ids[ids == 1])).tolist()) == {-1, 1}
    # Pixels that showed instance 0 or 2 (or the wall) and no part of instance 1 now show the background.
    empty = only_one["accumulation"][..., 0] == 0
    assert empty.sum() > 0.5 * WIDTH * HEIGHT
    torch.testing.assert_close(isolated["rgb"][empty], scene.background.expand(int(empty.sum()), 3))
    assert not torch.allclose(isolated["rgb"], base["rgb"])
    assert torch.equal(isolated[OUTPUT_INSTANCES], palette(direct_id_map(scene.subset(ids == 1), view, ids[ids == 1])))

    state.set_display(DISPLAY_HIDE)
    hidden = state.render_outputs(scene, view, base, wanted={OUTPUT_INSTANCES})
    assert torch.equal(hidden["rgb"], render_rgb(scene.subset(ids != 1), view)["rgb"])
    assert 1 not in torch.unique(direct_id_map(scene.subset(ids != 1), view, ids[ids != 1])).tolist()
    hidden_colours = {tuple(c) for c in hidden[OUTPUT_INSTANCES].reshape(-1, 3).tolist()}
    assert tuple(palette(torch.tensor([1]))[0].tolist()) not in hidden_colours

    state.set_display(DISPLAY_ALL)
    assert "rgb" not in state.render_outputs(scene, view, base, wanted=set())


def test_crop_limits_the_rendered_gaussians(scene_and_ids, front, state):
    scene, ids, _ = scene_and_ids
    view, base, _ = front
    crop = scene.gaussians.means[:, 0] < 0.45  # keeps instance 0 and 1, drops instance 2 and part of the wall
    state.select(0)
    state.set_display(DISPLAY_HIDE)
    outputs = state.render_outputs(scene, view, base, wanted=set(), crop=crop)
    assert torch.equal(outputs["rgb"], render_rgb(scene.subset(crop & (ids != 0)), view)["rgb"])


# ------------------------------------------------------------------------------------------------
# votes


def test_vote_colours_picture_where_gaussians_vote():
    votes = torch.tensor([[0.0, 0.0, 0.0]] * 5 + [[1.0, 2.0, 3.0]] * 5 + [[9.0, 9.0, 9.0], [math.nan, 0.0, 0.0]])
    foreground = torch.tensor([True] * 10 + [False, True])
    colours = vote_colours(votes, foreground)
    assert torch.equal(colours[:5], colours[0].expand(5, 3)) and torch.equal(colours[5:10], colours[5].expand(5, 3))
    assert (colours[0] - colours[5]).abs().min() > 0.9  # opposite corners of the colour cube
    assert torch.equal(colours[10:], torch.full((2, 3), VOTE_BACKGROUND_GREY))
    assert torch.isfinite(colours).all() and colours.min() >= 0 and colours.max() <= 1
    assert torch.equal(
        vote_colours(votes[:2], torch.zeros(2, dtype=torch.bool)), torch.full((2, 3), VOTE_BACKGROUND_GREY)
    )
    with pytest.raises(ValueError, match="votes"):
        vote_colours(votes[:, :2])


def test_votes_output_shows_each_instance_in_its_vote_colour(scene_and_ids, front, state):
    scene, ids, _ = scene_and_ids
    view, base, _ = front
    picture = state.render_outputs(scene, view, base, wanted={OUTPUT_VOTES})[OUTPUT_VOTES]
    assert state.cluster_calls == 0  # the votes picture needs no clustering
    assert torch.equal(picture, render_vote_picture(scene, view, 0))
    colours = vote_colours(
        scene.gaussians.means + scene.gaussians.vote_offsets[:, 0], scene.gaussians.vote_support[:, 0] > 0
    )
    # Where one instance covers a pixel almost alone, the picture shows that instance's vote colour.
    one_hot = F.one_hot(ids.clamp(min=0), 3).float() * (ids >= 0)[:, None]
    weights, _, _ = rasterize(
        scene.gaussians.means,
        scene.gaussians.quats,
        scene.gaussians.scales,
        scene.gaussians.opacities,
        one_hot,
        view.viewmat[None],
        view.K[None],
        WIDTH,
        HEIGHT,
    )
    # picture = w_k * colour_k + (other colours and background, total weight 1 - w_k), all in [0, 1]
    for k in range(3):
        weight = weights[0, ..., k]
        mostly_k = weight > 0.9
        assert mostly_k.sum() >= 5
        colour_k = colours[ids == k].mean(dim=0)
        assert ((picture[mostly_k] - colour_k).abs() <= (1 - weight[mostly_k, None]) + 0.01).all()
    state.set_level("part")
    assert not torch.equal(
        state.render_outputs(scene, view, {"rgb": picture}, wanted={OUTPUT_VOTES})[OUTPUT_VOTES], picture
    )


# ------------------------------------------------------------------------------------------------
# instances from clustering the votes


def test_instances_come_from_clustering_the_votes_lazily(scene_and_ids, front):
    scene, ids, part_ids = scene_and_ids
    view, base, _ = front
    state = InstanceViewerState(("instance", "part"))  # the real clustering (HDBSCAN)
    state.render_outputs(scene, view, base, wanted=set())
    assert state.instances is None  # nothing asked for instances yet
    state.render_outputs(scene, view, base, wanted={OUTPUT_OVERLAY})
    assert state.cluster_calls == 1
    for level, truth in (("instance", ids), ("part", part_ids)):
        found = torch.from_numpy(state.instances.level(level).ids)
        assert ((found >= 0) == (truth >= 0)).all()
        pairs = set(zip(truth[truth >= 0].tolist(), found[truth >= 0].tolist()))
        assert len(pairs) == len(set(truth[truth >= 0].tolist())) == len({f for _, f in pairs})  # same partition
    assert "3 instances at level 'instance'" in state.status
    state.render_outputs(scene, view, base, wanted={OUTPUT_INSTANCES})
    assert state.cluster_calls == 1  # cached
    state.request_instances()
    state.render_outputs(scene, view, base, wanted=set())
    assert state.cluster_calls == 2  # the "Compute instances" button
    fewer = scene.subset(torch.arange(scene.num_gaussians) % 7 != 0)
    state.render_outputs(fewer, view, base, wanted={OUTPUT_INSTANCES})
    assert state.cluster_calls == 3 and state.instances.num_gaussians == fewer.num_gaussians  # densified/pruned model


def test_level_switch_uses_that_levels_ids_and_clears_the_selection(scene_and_ids, front, state):
    scene, ids, part_ids = scene_and_ids
    view, base, _ = front
    state.select(2)
    state.set_level("part")
    assert state.selected is None
    instances = state.render_outputs(scene, view, base, wanted={OUTPUT_INSTANCES})[OUTPUT_INSTANCES]
    assert torch.equal(instances, palette(direct_id_map(scene, view, part_ids)))
    state.select(7)
    state.render_outputs(scene, view, base, wanted=set())
    assert state.selected is None and "no instance 7" in state.status
    with pytest.raises(ValueError, match="unknown vote level"):
        state.set_level("object")


def test_no_votes_shows_a_status_instead_of_failing(scene_and_ids, front):
    scene, _, _ = scene_and_ids
    view, base, _ = front
    plain = ViewerScene(scene.gaussians._replace(vote_offsets=None, vote_support=None), scene.background)
    state = InstanceViewerState(("instance",))
    outputs = state.render_outputs(plain, view, base, wanted={OUTPUT_OVERLAY, OUTPUT_VOTES})
    assert outputs[OUTPUT_OVERLAY] is base["rgb"] and outputs[OUTPUT_VOTES] is base["rgb"]
    assert "no vote offsets" in state.status
    state.render_outputs(plain, view, base, wanted={OUTPUT_OVERLAY})
    assert state.cluster_calls == 1 and "no vote offsets" in state.status  # not retried every frame
    state.request_instances()
    state.render_outputs(plain, view, base, wanted={OUTPUT_OVERLAY})
    assert state.cluster_calls == 2  # the button retries
    with pytest.raises(ValueError, match="unknown viewer outputs"):
        state.render_outputs(scene, view, base, wanted={"instance_overlays"})


# ------------------------------------------------------------------------------------------------
# text query


COLOUR_WORDS = {"red": 0, "green": 1, "blue": 2}


class MeanColourEncoder:
    """Deterministic encoder: an image's feature is its mean non-black colour; a colour word is its axis."""

    config = {"kind": "mean_colour_test"}

    def encode_images(self, crops):
        rows = []
        for crop in crops:
            pixels = torch.from_numpy(crop.reshape(-1, 3).astype(np.float32))
            rows.append(pixels[pixels.sum(dim=1) > 0].mean(dim=0))
        return F.normalize(torch.stack(rows), dim=-1)

    def encode_text(self, texts):
        rows = [
            F.one_hot(torch.tensor(COLOUR_WORDS[t]), 3).float() if t in COLOUR_WORDS else torch.ones(3) for t in texts
        ]
        return F.normalize(torch.stack(rows), dim=-1)


def test_text_query_selects_the_matching_instance(scene_and_ids):
    scene, ids, part_ids = scene_and_ids
    views = [make_view(eye) for eye in ((0.0, 0.0, 0.0), (1.0, 0.3, 0.5))]
    images = [(render_rgb(scene, v)["rgb"].numpy() * 255).round().astype(np.uint8) for v in views]
    made = []
    state = InstanceViewerState(
        ("instance", "part"),
        cluster_fn=lambda s, levels: known_instances(s, ids, part_ids),
        encoder_factory=lambda: made.append(1) or MeanColourEncoder(),
        feature_views=lambda: list(zip(views, images)),
    )
    base = render_rgb(scene, views[0])
    for word, expected in (("green", 1), ("blue", 2), ("red", 0)):
        state.request_query(word)
        state.render_outputs(scene, views[0], base, wanted=set())
        assert state.selected == expected, (word, state.status)
    assert made == [1]  # the encoder is loaded once

    no_clip = InstanceViewerState(("instance",), cluster_fn=lambda s, levels: known_instances(s, ids, part_ids))
    no_clip.select(2)
    no_clip.request_query("green")
    no_clip.render_outputs(scene, views[0], base, wanted=set())
    assert no_clip.selected == 2 and "clip-checkpoint" in no_clip.status


# ------------------------------------------------------------------------------------------------
# export


def test_export_selected_writes_the_instance_ply(tmp_path, scene_and_ids, front, state):
    scene, ids, _ = scene_and_ids
    n = scene.num_gaussians
    params = {
        "means": scene.gaussians.means,
        "features_dc": torch.randn(n, 3),
        "features_rest": torch.randn(n, 3, 3),
        "opacities": torch.logit(scene.gaussians.opacities)[:, None],
        "scales": torch.log(scene.gaussians.scales),
        "quats": scene.gaussians.quats,
    }
    with pytest.raises(ValueError, match="nothing selected"):
        state.export_selected(params, tmp_path)
    state.render_outputs(scene, front[0], front[1], wanted=set())
    state.request_instances()
    state.render_outputs(scene, front[0], front[1], wanted=set())
    state.select(2)
    path = state.export_selected(params, tmp_path / "out")
    written = read_gaussian_ply(path)
    np.testing.assert_array_equal(written["means"], scene.gaussians.means[ids == 2].numpy())
    np.testing.assert_allclose(written["features_rest"], params["features_rest"][ids == 2].numpy())
    assert not list((tmp_path / "out").glob("*.tmp"))
    with pytest.raises(ValueError, match="Compute instances"):
        state.export_selected({k: v[:-1] for k, v in params.items()}, tmp_path)
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="is a file"):
        state.export_selected(params, tmp_path / "file")


def test_overlay_rejects_mismatched_inputs():
    with pytest.raises(ValueError, match="rgb must be"):
        overlay_instances(torch.zeros(4, 5, 3), torch.zeros(5, 4, dtype=torch.long))
    with pytest.raises(ValueError, match="integer"):
        overlay_instances(torch.zeros(4, 5, 3), torch.zeros(4, 5))
    with pytest.raises(ValueError, match="opacity"):
        overlay_instances(torch.zeros(4, 5, 3), torch.zeros(4, 5, dtype=torch.long), opacity=1.5)


def state_cpu_instances(scene, view, base, ids, part_ids):
    state = InstanceViewerState(
        ("instance", "part"), cluster_fn=lambda s, levels: known_instances(scene, ids, part_ids)
    )
    return state.render_outputs(scene, view, base, wanted={OUTPUT_INSTANCES})[OUTPUT_INSTANCES]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device (the GPU path renders with gsplat)")
def test_viewer_outputs_on_cuda_agree_with_the_cpu_renderer(scene_and_ids, front):
    scene, ids, part_ids = scene_and_ids
    view, base, id_map = front
    cuda_view = PinholeView(view.viewmat.cuda(), view.K.cuda(), view.width, view.height)
    cuda_scene = scene.to("cuda")
    state = InstanceViewerState(
        ("instance", "part"), cluster_fn=lambda s, levels: known_instances(scene, ids, part_ids)
    )
    cuda_base = render_rgb(cuda_scene, cuda_view)  # gsplat's CUDA rasteriser
    torch.testing.assert_close(cuda_base["rgb"].cpu(), base["rgb"], rtol=0, atol=2e-3)
    outputs = state.render_outputs(cuda_scene, cuda_view, cuda_base, wanted=set(VIEWER_OUTPUTS))
    assert all(outputs[name].is_cuda for name in VIEWER_OUTPUTS)
    cuda_map = direct_id_map(cuda_scene, cuda_view, ids.cuda()).cpu()
    assert (cuda_map == id_map).float().mean() > 0.99  # pixels at a 0.5 weight boundary may flip
    # the viewer's id render and direct_id_map are two gsplat passes: weights within float error of
    # the 0.5 threshold may fall either side, so hold them to the same 99% as above
    # (colours are byte/255 on either device: equal up to float rounding)
    same_colour = torch.isclose(outputs[OUTPUT_INSTANCES].cpu(), palette(cuda_map), rtol=0, atol=1e-6).all(dim=-1)
    differ = ~same_colour
    assert same_colour.float().mean() > 0.99, (
        f"{int(differ.sum())} pixels differ; there the id map says {torch.unique(cuda_map[differ]).tolist()}, "
        f"the output shows colours {torch.unique(outputs[OUTPUT_INSTANCES].cpu()[differ], dim=0).tolist()[:6]}, "
        f"the CPU state {torch.unique(state_cpu_instances(scene, view, base, ids, part_ids)[differ], dim=0).tolist()[:6]}"
    )
    torch.testing.assert_close(outputs[OUTPUT_VOTES].cpu(), render_vote_picture(scene, view, 0), rtol=0, atol=2e-3)


# ------------------------------------------------------------------------------------------------
# nerfstudio glue on a real model


def test_glue_on_a_votesplat_model(scene_and_ids, monkeypatch):
    from nerfstudio.cameras.cameras import Cameras
    from nerfstudio.data.scene_box import SceneBox
    from nerfstudio.models import splatfacto
    from nerfstudio.viewer.utils import parse_object
    from nerfstudio.viewer.viewer_elements import ViewerControl, ViewerElement

    from votesplat_ns.ns.model import VoteSplatModelConfig
    from votesplat_ns.ns.run import camera_view
    from votesplat_ns.ns.viewer import VoteSplatViewerState, scene_from_model

    # splatfacto's get_viewmat is torch.compile'd; compiling it costs ~10 s on CPU and tests nothing here (under the
    # untraced wrapper of ns/patches.py when an earlier test built a model)
    compiled = getattr(splatfacto.get_viewmat, "__wrapped__", splatfacto.get_viewmat)
    monkeypatch.setattr(splatfacto, "get_viewmat", getattr(compiled, "_torchdynamo_orig_callable", compiled))
    scene, ids, part_ids = scene_and_ids
    torch.manual_seed(0)
    points = scene.gaussians.means.clone()
    model = VoteSplatModelConfig(sh_degree=1, background_color="black", vote_levels=("instance", "part")).setup(
        scene_box=SceneBox(aabb=torch.tensor([[-4.0, -4.0, 0.0], [4.0, 4.0, 8.0]])),
        num_train_data=2,
        seed_points=(points, (torch.rand(points.shape[0], 3) * 255).to(torch.uint8)),
    )
    model.eval()
    with torch.no_grad():
        model.gauss_params["vote_offsets"].copy_(scene.gaussians.vote_offsets)
        model.gauss_params["vote_support"].copy_(scene.gaussians.vote_support)
        model.gauss_params["opacities"].fill_(1.0)
    viewer_state = VoteSplatViewerState(model)
    model.viewer_state = viewer_state

    found = [path for path, _ in parse_object(model, ViewerElement, "Custom Elements")]
    assert found == sorted(found) and len(found) == 8  # laid out in this (alphabetical) order
    assert any(isinstance(c, ViewerControl) for _, c in parse_object(model, ViewerControl, "Custom Elements"))
    assert model.instance_gui_5_query.disabled and "clip-checkpoint" in model.instance_gui_5_query.default_value
    assert model.instance_gui_0_level.options == ["instance", "part"]

    c2w = torch.linalg.inv(look_at((0.0, 0.0, 0.0)))[:3]
    c2w = c2w * torch.tensor([1.0, -1.0, -1.0, 1.0])  # OpenCV -> nerfstudio (OpenGL) camera axes
    camera = Cameras(
        camera_to_worlds=c2w[None], fx=40.0, fy=40.0, cx=WIDTH / 2, cy=HEIGHT / 2, width=WIDTH, height=HEIGHT
    )
    with torch.no_grad():
        outputs = model.get_outputs(camera)
    assert viewer_state.extra_outputs(camera, outputs) == {}  # not a viewer render thread: nothing added

    mirror = render_rgb(scene_from_model(model), camera_view(camera))
    torch.testing.assert_close(mirror["rgb"], outputs["rgb"], rtol=0, atol=1e-6)

    extra = viewer_state.viewer_outputs(camera, outputs, {OUTPUT_OVERLAY})
    assert set(extra) == set(VIEWER_OUTPUTS)
    assert extra[OUTPUT_OVERLAY].shape == (HEIGHT, WIDTH, 3) and extra[OUTPUT_INSTANCES] is outputs["rgb"]
    assert viewer_state.state.num_instances() == 3
    assert model.instance_gui_7_status.value == "3 instances at level 'instance'"

    # GUI callbacks only record state; the next render applies it.
    model.instance_gui_3_selected.value = 1
    model.instance_gui_3_selected.cb_hook(model.instance_gui_3_selected)
    model.instance_gui_4_display.value = DISPLAY_ISOLATE
    model.instance_gui_4_display.cb_hook(model.instance_gui_4_display)
    assert viewer_state.state.selected == 1 and viewer_state.state.display == DISPLAY_ISOLATE
    isolated = viewer_state.viewer_outputs(camera, outputs, set())
    selected = torch.from_numpy(viewer_state.state.instances.level("instance").ids) == 1
    expected = render_rgb(scene_from_model(model).subset(selected), camera_view(camera))["rgb"]
    assert torch.equal(isolated["rgb"], expected) and isolated[OUTPUT_OVERLAY] is isolated["rgb"]

    model.instance_gui_0_level.value = "part"
    model.instance_gui_0_level.cb_hook(model.instance_gui_0_level)
    viewer_state.viewer_outputs(camera, outputs, set())
    assert viewer_state.state.selected is None and model.instance_gui_3_selected.value == -1

    # Instance features are built from training views, at most MAX_FEATURE_VIEW_SIDE pixels wide.
    class TrainDataset:
        cameras = Cameras(
            camera_to_worlds=c2w[None].expand(3, 3, 4), fx=800.0, fy=800.0, cx=512.0, cy=400.0, width=1024, height=800
        )

        def __len__(self):
            return 3

        def get_numpy_image(self, index):
            return np.full((800, 1024, 3), index, dtype=np.uint8)

    model.instance_gui_viewer_control.viewer = SimpleNamespace(
        pipeline=SimpleNamespace(datamanager=SimpleNamespace(train_dataset=TrainDataset()))
    )
    views = viewer_state._feature_views()
    assert [int(image[0, 0, 0]) for _, image in views] == [0, 1, 2]
    assert all((view.width, view.height) == (512, 400) and image.shape == (400, 512, 3) for view, image in views)
    torch.testing.assert_close(views[0][0].K, torch.tensor([[400.0, 0, 256], [0, 400, 200], [0, 0, 1]]))

    # With a CLIP checkpoint configured the text box is live; a missing file is reported, not raised.
    model.config.clip_checkpoint = "/nonexistent/open_clip_weights.bin"
    clip_state = VoteSplatViewerState(model)
    assert not model.instance_gui_5_query.disabled
    model.instance_gui_5_query.value = "red mug"
    model.instance_gui_5_query.cb_hook(model.instance_gui_5_query)
    clip_state.viewer_outputs(camera, outputs, set())
    assert "CLIP checkpoint not found" in model.instance_gui_7_status.value
