"""The plugin's fixes for nerfstudio 1.1.5: checkpoints under torch >= 2.6, offline LPIPS, CPU .cuda()."""

import threading

import numpy as np
import pytest
import torch

import votesplat_ns  # noqa: F401  (registers the safe globals on import)
from votesplat_ns.ns import compat, patches


def test_checkpoint_with_numpy_scalars_loads_with_weights_only(tmp_path):
    # What nerfstudio's trainer saves: numpy scalars and arrays beside tensors.
    state = {
        "step": np.int64(1234),
        "pipeline": {"gauss_params.means": torch.randn(4, 3)},
        "schedulers": {"means": {"base_lrs": [np.float64(1.6e-4)], "last_epoch": np.int64(3)}},
        "extra": np.arange(5, dtype=np.float32),
    }
    path = tmp_path / "step-000001234.ckpt"
    torch.save(state, path)
    loaded = torch.load(path, map_location="cpu", weights_only=True)
    assert int(loaded["step"]) == 1234
    assert torch.equal(loaded["pipeline"]["gauss_params.means"], state["pipeline"]["gauss_params.means"])
    assert np.array_equal(loaded["extra"], state["extra"])


def test_lpips_is_skipped_with_a_warning_when_alexnet_is_not_cached(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    monkeypatch.delenv("VOTESPLAT_ALLOW_DOWNLOADS", raising=False)
    compat._warn_once.cache_clear()
    with pytest.warns(RuntimeWarning, match="LPIPS disabled"):
        metric = compat.make_lpips_metric()
    assert isinstance(metric, compat.UnavailableMetric)
    assert torch.isnan(metric(torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 8)))


def test_offline_lpips_context_replaces_the_constructor_only_inside(tmp_path, monkeypatch):
    import torchmetrics.image.lpip as lpip_module

    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    original = lpip_module.LearnedPerceptualImagePatchSimilarity
    compat._warn_once.cache_clear()
    with pytest.warns(RuntimeWarning), patches.offline_lpips():
        metric = lpip_module.LearnedPerceptualImagePatchSimilarity(normalize=True)
    assert isinstance(metric, compat.UnavailableMetric)
    assert lpip_module.LearnedPerceptualImagePatchSimilarity is original


@pytest.mark.skipif(torch.cuda.is_available(), reason="the .cuda() fallback only applies without a CUDA device")
def test_cuda_calls_stay_on_cpu_is_reentrant_across_threads():
    original = torch.Tensor.cuda
    entered = threading.Event()
    release = threading.Event()

    def hold():
        with patches.cuda_calls_stay_on_cpu():
            entered.set()
            release.wait(5)

    worker = threading.Thread(target=hold)
    worker.start()
    entered.wait(5)
    with patches.cuda_calls_stay_on_cpu():
        x = torch.ones(2)
        assert x.cuda() is x
    # the other thread is still inside: the patch must still be active
    assert torch.ones(1).cuda().device.type == "cpu"
    release.set()
    worker.join()
    assert torch.Tensor.cuda is original
    with pytest.raises((AssertionError, RuntimeError)):
        torch.ones(1).cuda()
