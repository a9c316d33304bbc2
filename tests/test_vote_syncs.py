"""Host synchronisations of a vote step, counted at the dispatcher (forward and backward).

On a GPU every host read stalls the training step until the queue drains; on CPU the same
reads are counted with tests/op_counter.py's OpCounter (a TorchDispatchMode, so
autograd's backward ops are seen too, plus Tensor.tolist).
"""

from __future__ import annotations

import pytest
import torch
from op_counter import OpCounter, model_step
from test_vote_render import call, random_scene, sample_pixels, tile_lists_gsplat, with_level_votes

from votesplat_ns.core import vote_render
from votesplat_ns.core.vote_maps import voting_pixels
from votesplat_ns.core.vote_render import VoteRenderOptions, render_votes_tiled, vote_losses


@pytest.fixture(scope="module")
def scene():
    width, height, tile_size = 40, 32, 8
    base = random_scene(120, width, height, seed=5)
    pixel_xy = sample_pixels(width, height, seed=6, extra=60)
    return base, pixel_xy, tile_size, tile_lists_gsplat(base, width, height, tile_size)


@pytest.mark.parametrize("levels", [1, 4])
@pytest.mark.parametrize("distortion", ["l1", "l1_pixels"])
@pytest.mark.parametrize("check_inputs", [False, True])
def test_one_host_read_per_vote_pass(scene, levels, distortion, check_inputs):
    """A one-step walk (the GPU's default width), all levels, forward and backward: the walk's one read
    (it sizes the member table and carries the input checks), plus one for vote_losses' own checks."""
    base, pixel_xy, tile_size, (offsets, flatten_ids) = scene
    leveled = with_level_votes(base, levels=levels) if levels > 1 else base
    votes = leveled["votes"].clone().requires_grad_()
    target = pixel_xy[:, None, :].expand(-1, levels, -1) + 3.0
    valid = torch.ones(len(pixel_xy), levels, dtype=torch.bool)
    if levels == 1:
        target, valid = target[:, 0], valid[:, 0]
    options = VoteRenderOptions(distortion=distortion)

    def step():
        out = call(
            render_votes_tiled,
            {**leveled, "votes": votes},
            pixel_xy,
            options,
            isect_offsets=offsets,
            flatten_ids=flatten_ids,
            tile_size=tile_size,
            chunk=10_000,
        )
        assert int(out.count.max()) > 1
        losses = vote_losses(out, target, valid, options, check_inputs=check_inputs)
        return losses["vote"].sum() + losses["distortion"].sum()

    with OpCounter() as counter:
        loss = step()
        with counter.phase("backward"):
            loss.backward()
    syncs = {phase: names for phase, names in counter.syncs.items() if names}
    # the one read in the walk phase; the test's own int(count.max()) is counted under "other"
    assert len(syncs.pop("walk")) == 1, counter.syncs
    assert len(syncs.pop("other")) == 1, counter.syncs
    if check_inputs:
        assert len(syncs.pop("loss checks")) == 1, counter.syncs
    assert syncs == {}, syncs
    assert counter.ops["backward"] > 0 and votes.grad.abs().sum() > 0


def test_bad_inputs_still_raise_from_the_walks_read(scene):
    """The input checks ride on the walk's host read: bad values still raise before anything is returned."""
    base, pixel_xy, tile_size, (offsets, flatten_ids) = scene
    kwargs = dict(isect_offsets=offsets, flatten_ids=flatten_ids, tile_size=tile_size, chunk=10_000)
    votes = base["votes"].clone()
    votes[7, 2] = float("inf")
    with pytest.raises(ValueError, match="votes contain NaN or inf"):
        call(render_votes_tiled, {**base, "votes": votes}, pixel_xy, None, **kwargs)
    bad_pixels = pixel_xy.clone()
    bad_pixels[3, 0] = float("nan")
    with pytest.raises(ValueError, match="pixel_xy contains NaN or inf"):
        call(render_votes_tiled, base, bad_pixels, None, **kwargs)
    with pytest.raises(ValueError, match="flatten_ids must index"):
        call(render_votes_tiled, base, pixel_xy, None, **{**kwargs, "flatten_ids": flatten_ids - 5})
    with pytest.raises(ValueError, match="isect_offsets point outside"):
        call(render_votes_tiled, base, pixel_xy, None, **{**kwargs, "isect_offsets": offsets - 10_000})
    out = call(render_votes_tiled, base, pixel_xy, None, **kwargs)
    broken = out._replace(projected_vote=torch.where((out.count > 0)[:, None], float("nan"), out.projected_vote))
    with pytest.raises(ValueError, match="the vote render contains NaN or inf"):
        vote_losses(broken, pixel_xy.clone(), torch.ones(len(pixel_xy), dtype=torch.bool))


@pytest.fixture(scope="module")
def vote_model():
    return model_step(levels=2, n=600, width=64, height=48, pixels=256)


def test_model_vote_step_reads_the_host_once(vote_model, monkeypatch):
    """VoteSplatModel.vote_loss_terms, forward and backward, at the GPU's walk width: only the walk's read."""
    model, step = vote_model
    monkeypatch.setattr(vote_render, "AUTO_PAIRS_PER_STEP_CPU", vote_render.AUTO_PAIRS_PER_STEP)
    with OpCounter() as counter:
        loss = step(seed=0)
        with counter.phase("backward"):
            loss.backward()
    syncs = {phase: names for phase, names in counter.syncs.items() if names}
    assert {phase: len(names) for phase, names in syncs.items()} == {"walk": 1}, syncs
    assert loss.item() > 0
    assert model.gauss_params["vote_offsets"].grad.abs().sum() > 0


def test_model_view_without_masks_gives_zero_connected_losses(vote_model):
    """No mask in the view: both losses are 0, part of the graph, and give the offsets a zero gradient
    (no host read decides it)."""
    model, _ = vote_model
    labels = torch.zeros(2, 48, 64, dtype=torch.int32)
    centroids = torch.full((2, 5, 2), float("nan"))
    model.gauss_params["vote_offsets"].grad = None
    batch = {"vote_labels": labels, "vote_centroids": centroids, "vote_pixels": voting_pixels(labels, centroids)}
    assert batch["vote_pixels"].numel() == 0
    loss, terms = model.vote_loss_terms(batch)
    loss.backward()
    assert loss.item() == 0.0 and not terms.any()
    grad = model.gauss_params["vote_offsets"].grad
    assert grad is not None and not grad.any()


def test_vote_losses_computed_with_the_metrics_are_the_loss_dicts(monkeypatch):
    """get_metrics_dict computes the step's vote losses once and get_loss_dict of the same batch returns
    them; a batch that did not go through get_metrics_dict gets its own."""
    from nerfstudio.models.splatfacto import SplatfactoModel

    model, _ = model_step(levels=2, n=300, width=32, height=24, pixels=64)
    monkeypatch.setattr(SplatfactoModel, "get_metrics_dict", lambda self, outputs, batch: {})
    monkeypatch.setattr(SplatfactoModel, "get_loss_dict", lambda self, outputs, batch, metrics_dict=None: {})
    calls = []
    terms = model.vote_loss_terms
    monkeypatch.setattr(model, "vote_loss_terms", lambda batch, **kw: calls.append(batch) or terms(batch, **kw))
    labels = torch.zeros(2, 24, 32, dtype=torch.int32)
    labels[:, 4:20, 4:28] = 1
    centroids = torch.tensor([[[float("nan")] * 2, [15.0, 11.0]]] * 2)
    batch = {"vote_labels": labels, "vote_centroids": centroids, "vote_pixels": voting_pixels(labels, centroids)}
    other = dict(batch)

    metrics = model.get_metrics_dict({}, batch)
    early = model.get_loss_dict({}, batch)
    assert len(calls) == 1 and set(early) == {"vote"} and set(metrics) == {"vote_l1", "vote_distortion"}
    assert early["vote"].requires_grad and not metrics["vote_l1"].requires_grad
    torch.testing.assert_close(metrics["vote_l1"] + metrics["vote_distortion"], early["vote"].detach())
    model.get_metrics_dict({}, batch)
    late = model.get_loss_dict({}, other)  # not the batch the metrics saw: computed again
    assert len(calls) == 3 and calls[-1] is other and set(late) == set(early)
    model.eval()
    model.get_metrics_dict({}, batch)
    assert model.get_loss_dict({}, batch) == {} and len(calls) == 3  # no vote outside training
