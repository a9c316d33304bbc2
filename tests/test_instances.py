"""Instance dictionary invariants and files, colours, instance-id rendering and pictures."""

import json

import numpy as np
import pytest
import torch
from PIL import Image

from votesplat_ns.core.instances import (
    IDS_NAME,
    MANIFEST_NAME,
    InstanceSet,
    LevelInstances,
    instance_colors,
    instance_picture,
    render_instance_ids,
    save_instance_picture,
)


def brute_force_rasterize(means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree=None, **_):
    """Literal gsplat 1.4 classic rasterisation of one camera: per-pixel front-to-back compositing."""
    assert sh_degree is None
    viewmat, K = viewmats[0].double(), Ks[0].double()
    q = torch.nn.functional.normalize(quats.double(), dim=-1)
    w, x, y, z = q.unbind(-1)
    rot = torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)
    m = rot * scales.double()[:, None, :]
    cov_world = m @ m.transpose(1, 2)
    cam = means.double() @ viewmat[:3, :3].T + viewmat[:3, 3]
    cov_cam = viewmat[:3, :3] @ cov_world @ viewmat[:3, :3].T
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tx, ty, tz = cam.unbind(-1)
    jac = torch.zeros(means.shape[0], 2, 3, dtype=torch.float64)
    jac[:, 0, 0], jac[:, 0, 2] = fx / tz, -fx * tx / tz**2
    jac[:, 1, 1], jac[:, 1, 2] = fy / tz, -fy * ty / tz**2
    cov2d = jac @ cov_cam @ jac.transpose(1, 2) + 0.3 * torch.eye(2, dtype=torch.float64)
    conic = torch.linalg.inv(cov2d)
    mean2d = torch.stack([fx * tx / tz + cx, fy * ty / tz + cy], dim=-1)
    py, px = torch.meshgrid(
        torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64), indexing="ij"
    )
    pixels = torch.stack([px + 0.5, py + 0.5], dim=-1).reshape(-1, 2)
    out = torch.zeros(pixels.shape[0], colors.shape[-1], dtype=torch.float64)
    transmittance = torch.ones(pixels.shape[0], dtype=torch.float64)
    active = torch.ones(pixels.shape[0], dtype=torch.bool)
    for i in torch.argsort(tz).tolist():
        if tz[i] <= 0.01:
            continue
        d = mean2d[i] - pixels
        sigma = (
            0.5 * (conic[i, 0, 0] * d[:, 0] ** 2 + conic[i, 1, 1] * d[:, 1] ** 2) + conic[i, 0, 1] * d[:, 0] * d[:, 1]
        )
        alpha = torch.clamp(opacities[i].double() * torch.exp(-sigma), max=0.99)
        use = active & (sigma >= 0) & (alpha >= 1.0 / 255.0)
        next_t = transmittance * (1 - alpha)
        stop = use & (next_t <= 1e-4)
        active = active & ~stop
        use = use & ~stop
        out[use] += colors[i].double() * (alpha * transmittance)[use, None]
        transmittance = torch.where(use, next_t, transmittance)
    alphas = (1 - transmittance).reshape(1, height, width, 1)
    return out.reshape(1, height, width, -1).to(colors.dtype), alphas.float(), {}


def gaussians(rows):
    """rows of (x, y, z, scale, opacity, instance id) -> tensors for render_instance_ids."""
    data = torch.tensor([r[:5] for r in rows], dtype=torch.float32)
    n = data.shape[0]
    quats = torch.tensor([[1.0, 0, 0, 0]] * n)
    return data[:, :3], quats, data[:, 3:4].repeat(1, 3), data[:, 4], torch.tensor([r[5] for r in rows])


WIDTH, HEIGHT = 32, 24
K = torch.tensor([[20.0, 0, 16.0], [0, 20.0, 12.0], [0, 0, 1.0]])
VIEWMAT = torch.eye(4)


def pixel_of(x, y, z):
    return int(20 * y / z + 12), int(20 * x / z + 16)  # (row, col) holding the projected point


def test_render_instance_ids_occlusion_and_threshold():
    rows = [
        (-0.6, 0.0, 3.0, 0.5, 0.99, 0),  # instance 0, left (pixel column 12)
        (0.6, 0.0, 3.0, 0.5, 0.99, 1),  # instance 1, right (column 20)
        (0.3, 0.0, 2.0, 0.1, 0.99, -1),  # a small background Gaussian in front of instance 1 (column 19)
        (-0.6, 0.0, 5.0, 0.3, 0.99, 2),  # instance 2, hidden behind instance 0
    ]
    means, quats, scales, opacities, ids = gaussians(rows)
    id_map = render_instance_ids(brute_force_rasterize, means, quats, scales, opacities, ids, VIEWMAT, K, WIDTH, HEIGHT)
    assert id_map.shape == (HEIGHT, WIDTH) and id_map.dtype == torch.long
    assert id_map[pixel_of(-0.6, 0.0, 3.0)] == 0
    assert id_map[pixel_of(0.3, 0.0, 2.0)] == -1  # the background Gaussian covers it
    assert id_map[12, 21] == 1  # instance 1 beside the occluder
    assert id_map[0, 0] == -1 and id_map[HEIGHT - 1, WIDTH - 1] == -1  # empty space
    assert 2 not in id_map.unique().tolist()

    # the rule: argmax of the accumulated weights where it reaches min_weight
    weights, _, _ = brute_force_rasterize(
        means,
        quats,
        scales,
        opacities,
        torch.nn.functional.one_hot(ids.clamp(min=0), 3).float() * (ids >= 0)[:, None],
        VIEWMAT[None],
        K[None],
        WIDTH,
        HEIGHT,
    )
    best, arg = weights[0].max(-1)
    for min_weight in (0.5, 0.2, 0.9):
        expected = torch.where(best >= min_weight, arg, torch.full_like(arg, -1))
        got = render_instance_ids(
            brute_force_rasterize,
            means,
            quats,
            scales,
            opacities,
            ids.numpy(),
            VIEWMAT,
            K,
            WIDTH,
            HEIGHT,
            min_weight=min_weight,
        )
        assert torch.equal(got, expected)
    assert (
        render_instance_ids(
            brute_force_rasterize, means, quats, scales, opacities, ids, VIEWMAT, K, WIDTH, HEIGHT, min_weight=0.2
        )
        >= 0
    ).sum() > (id_map >= 0).sum()


def test_render_instance_ids_is_independent_of_chunking_and_id_values():
    rng = np.random.default_rng(0)
    rows = [
        (rng.uniform(-1, 1), rng.uniform(-0.7, 0.7), rng.uniform(2.5, 4), 0.12, 0.9, int(rng.integers(-1, 6)))
        for _ in range(40)
    ]
    means, quats, scales, opacities, ids = gaussians(rows)
    one_pass = render_instance_ids(
        brute_force_rasterize, means, quats, scales, opacities, ids, VIEWMAT, K, WIDTH, HEIGHT
    )
    per_instance = render_instance_ids(
        brute_force_rasterize, means, quats, scales, opacities, ids, VIEWMAT, K, WIDTH, HEIGHT, channels_per_pass=1
    )
    assert torch.equal(one_pass, per_instance)
    assert len(one_pass.unique()) > 3
    # sparse, large ids work the same as compact ones
    sparse = torch.where(ids >= 0, ids * 1000 + 7, ids)
    sparse_map = render_instance_ids(
        brute_force_rasterize, means, quats, scales, opacities, sparse, VIEWMAT, K, WIDTH, HEIGHT, channels_per_pass=2
    )
    assert torch.equal(sparse_map, torch.where(one_pass >= 0, one_pass * 1000 + 7, one_pass))
    nothing = render_instance_ids(
        brute_force_rasterize, means, quats, scales, opacities, torch.full_like(ids, -1), VIEWMAT, K, WIDTH, HEIGHT
    )
    assert (nothing == -1).all()


def test_render_instance_ids_bad_input():
    means, quats, scales, opacities, ids = gaussians([(0, 0, 3, 0.2, 0.9, 0)])
    with pytest.raises(ValueError, match="min_weight"):
        render_instance_ids(
            brute_force_rasterize, means, quats, scales, opacities, ids, VIEWMAT, K, WIDTH, HEIGHT, min_weight=0
        )
    with pytest.raises(ValueError, match="entries for 1 Gaussians"):
        render_instance_ids(
            brute_force_rasterize, means, quats, scales, opacities, torch.tensor([0, 1]), VIEWMAT, K, WIDTH, HEIGHT
        )


def make_level(name="instance", seed=0):
    rng = np.random.default_rng(seed)
    n = 60
    ids = rng.integers(-1, 4, size=n)
    foreground = ids >= 0
    foreground[:3] = True  # noise: foreground but in no instance
    ids[:3] = -1
    means = rng.normal(size=(n, 3))
    votes = np.where(foreground[:, None], rng.normal(size=(n, 3)), np.nan)
    return LevelInstances.from_ids(name, ids, foreground, means, votes, {"min_cluster_size": 10}), means, votes


def test_level_statistics_and_dictionary():
    level, means, votes = make_level()
    assert level.num_instances == 4 and level.num_noise == 3
    members = level.members()
    assert sorted(members) == [0, 1, 2, 3]
    covered = np.concatenate(list(members.values()))
    assert np.array_equal(np.sort(covered), np.flatnonzero(level.ids >= 0))  # each Gaussian in exactly one instance
    for i, idx in members.items():
        np.testing.assert_array_equal(idx, np.flatnonzero(level.ids == i))
        np.testing.assert_array_equal(level.gaussian_indices(i), idx)
        assert level.counts[i] == idx.size
        np.testing.assert_allclose(level.bbox_min[i], means[idx].min(0))
        np.testing.assert_allclose(level.bbox_max[i], means[idx].max(0))
        np.testing.assert_allclose(level.vote_centres[i], votes[idx].mean(0))
    with pytest.raises(ValueError, match="has instances 0..3"):
        level.gaussian_indices(4)


def test_ids_with_gaps_are_rejected():
    with pytest.raises(ValueError, match="without gaps"):
        LevelInstances.from_ids("x", np.array([0, 2, 2]), np.ones(3, bool), np.zeros((3, 3)), np.zeros((3, 3)))


def test_validate_catches_broken_invariants():
    level, _, _ = make_level()
    InstanceSet([level], 60).validate()
    broken = np.flatnonzero(~level.foreground)[0]
    level.ids[broken] = 0
    with pytest.raises(ValueError, match="background Gaussian"):
        InstanceSet([level], 60).validate()
    level, _, _ = make_level()
    level.counts = level.counts + 1
    with pytest.raises(ValueError, match="counts do not match"):
        InstanceSet([level], 60).validate()
    level, _, _ = make_level()
    with pytest.raises(ValueError, match="shape"):
        InstanceSet([level], 61).validate()


def test_parent_links_and_level_lookup():
    n = 8
    means = np.zeros((n, 3))
    coarse = LevelInstances.from_ids(
        "instance", np.array([0, 0, 0, 0, 1, 1, 1, -1]), np.array([1, 1, 1, 1, 1, 1, 1, 0], bool), means, means
    )
    fine = LevelInstances.from_ids("part", np.array([0, 0, 1, 1, 2, 2, 3, 3]), np.ones(n, bool), means, means)
    fine.link_parents(coarse)
    # part 3 has one Gaussian in instance 1 and one in none: Gaussians without a parent cannot vote
    np.testing.assert_array_equal(fine.parents, [0, 0, 1, 1])
    np.testing.assert_allclose(fine.parent_overlap, [1, 1, 1, 0.5])
    orphan = LevelInstances.from_ids("part", np.array([-1, -1, -1, -1, -1, -1, -1, 0]), np.ones(n, bool), means, means)
    orphan.link_parents(coarse)
    np.testing.assert_array_equal(orphan.parents, [-1])
    instances = InstanceSet([coarse, fine], n)
    instances.validate()
    assert (
        instances.level("part") is fine
        and instances.level(1) is fine
        and instances.level("1") is fine
        and instances.level(None) is coarse
    )
    with pytest.raises(ValueError, match="unknown vote level 'object'"):
        instances.level("object")
    assert instances.level("-1") is fine and instances.level_index(-1) == 1  # negative indices count from the end
    with pytest.raises(ValueError, match="out of range"):
        instances.level(2)


def test_save_and_load_round_trip(tmp_path):
    level, _, _ = make_level("instance", seed=1)
    part, _, _ = make_level("part", seed=2)
    instances = InstanceSet([level, part], 60, parent_levels=[None, "instance"])
    part.link_parents(level)
    manifest = instances.save(
        tmp_path, instance_extra={"instance": {0: {"file": "instances/instance_0000.ply"}}}, extra={"note": np.int64(3)}
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([MANIFEST_NAME, IDS_NAME])
    on_disk = json.loads((tmp_path / MANIFEST_NAME).read_text())
    assert on_disk == manifest and on_disk["note"] == 3
    assert on_disk["levels"][0]["instances"][0]["file"] == "instances/instance_0000.ply"
    assert on_disk["levels"][1]["parent_level"] == "instance"
    assert on_disk["levels"][0]["num_noise"] == 3
    assert (
        sum(i["count"] for i in on_disk["levels"][0]["instances"]) + on_disk["levels"][0]["num_noise"]
        == on_disk["levels"][0]["num_foreground"]
    )
    loaded = InstanceSet.load(tmp_path)
    loaded.validate()
    assert loaded.level_names == ("instance", "part")
    for a, b in zip(instances.levels, loaded.levels):
        for key in ("ids", "foreground", "counts", "bbox_min", "bbox_max", "vote_centres", "parents", "parent_overlap"):
            np.testing.assert_allclose(getattr(a, key), getattr(b, key), err_msg=key)
    with pytest.raises(ValueError, match="not found"):
        InstanceSet.load(tmp_path / "missing")


def test_confidence_is_saved_loaded_and_falls_back_to_the_size(tmp_path):
    level, _, _ = make_level("instance", seed=1)
    part, _, _ = make_level("part", seed=2)
    level.confidence = np.linspace(0.9, 0.1, level.num_instances)
    instances = InstanceSet([level, part], 60)
    instances.validate()
    instances.save(tmp_path)
    on_disk = json.loads((tmp_path / MANIFEST_NAME).read_text())
    assert [i["confidence"] for i in on_disk["levels"][0]["instances"]] == pytest.approx(level.confidence.tolist())
    assert all("confidence" not in i for i in on_disk["levels"][1]["instances"])  # absent, not made up
    loaded = InstanceSet.load(tmp_path)
    np.testing.assert_allclose(loaded.level("instance").confidence, level.confidence)
    np.testing.assert_allclose(loaded.level("instance").ranking_confidence(), level.confidence)
    assert loaded.level("part").confidence is None
    # without a confidence, instances rank by their share of the level's foreground Gaussians
    np.testing.assert_allclose(loaded.level("part").ranking_confidence(), part.counts / part.foreground.sum())
    level.confidence = np.ones(level.num_instances + 1)
    with pytest.raises(ValueError, match="confidence"):
        InstanceSet([level], 60).validate()


def test_colours_are_stable_and_distinct():
    ids = np.arange(-1, 40)
    colors = instance_colors(ids)
    assert colors.dtype == np.uint8 and colors.shape == (41, 3)
    assert tuple(colors[0]) == (0, 0, 0)
    assert len({tuple(c) for c in colors[1:]}) == 40
    # a pure function of the id: order, shape and container do not matter
    np.testing.assert_array_equal(instance_colors(ids[::-1])[::-1], colors)
    np.testing.assert_array_equal(instance_colors(torch.tensor([[3, 5]]))[0], colors[[4, 6]])
    # golden-ratio hue steps: fixed values, the same in every session
    assert tuple(instance_colors(np.array([0]))[0]) == (242, 36, 36)


def test_picture(tmp_path):
    maps = [np.array([[0, 1], [-1, 2]]), np.full((3, 4), 5)]
    images = [np.ones((2, 2, 3), np.float32), np.zeros((3, 4, 3), np.uint8)]
    picture = save_instance_picture(tmp_path / "p.png", maps, images, gap=2)
    assert picture.shape == (3 + 2 + 3, 2 + 2 + 4, 3)
    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / "p.png")), picture)
    np.testing.assert_array_equal(picture[5:7, 0:2], instance_colors(maps[0]))
    assert (picture[0:2, 0:2] == 255).all()
    assert instance_picture(maps).shape == (3, 2 + 4 + 4, 3)
    with pytest.raises(ValueError, match="one image per view"):
        instance_picture(maps, images[:1])
