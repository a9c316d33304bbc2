"""The plugin's fixes for nerfstudio 1.1.5: checkpoints under torch >= 2.6, metrics at first use and offline LPIPS,
CPU .cuda()."""

import subprocess
import sys
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


def test_metrics_at_first_use_replaces_torchmetrics_names_only_inside_and_builds_at_the_first_call(
    tmp_path, monkeypatch
):
    import torchmetrics.image
    import torchmetrics.image.lpip as lpip_module

    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    originals = torchmetrics.image.PeakSignalNoiseRatio, lpip_module.LearnedPerceptualImagePatchSimilarity
    compat._warn_once.cache_clear()
    with patches.metrics_at_first_use():
        psnr = torchmetrics.image.PeakSignalNoiseRatio(data_range=1.0)
        lpips = lpip_module.LearnedPerceptualImagePatchSimilarity(normalize=True)
    assert (torchmetrics.image.PeakSignalNoiseRatio, lpip_module.LearnedPerceptualImagePatchSimilarity) == originals
    assert isinstance(psnr, compat.MetricAtFirstUse) and psnr.built is None and lpips.built is None
    rendered, target = torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 8)
    assert torch.equal(psnr(rendered, target), originals[0](data_range=1.0)(rendered, target))
    with pytest.warns(RuntimeWarning, match="LPIPS disabled"):
        assert torch.isnan(lpips(rendered, target))  # AlexNet is not in this hub folder: no download
    assert isinstance(lpips.built, compat.UnavailableMetric)
    # the built metrics are not submodules: nothing of theirs goes into a checkpoint or to DDP
    assert not psnr.state_dict() and not list(psnr.parameters()) and not list(psnr.children())


METRICS_UNIMPORTED = """
import sys, torch
from votesplat_ns.ns import compat, patches
with patches.metrics_at_first_use():
    from torchmetrics.image import PeakSignalNoiseRatio
    from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity
    psnr, lpips = PeakSignalNoiseRatio(data_range=1.0), LearnedPerceptualImagePatchSimilarity(normalize=True)
assert isinstance(psnr, compat.MetricAtFirstUse) and isinstance(lpips, compat.MetricAtFirstUse)
assert not any(name.startswith("torchmetrics") for name in sys.modules), "the block imported torchmetrics"
rendered, target = torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 8)
value = psnr(rendered, target)
import torchmetrics.image
assert torchmetrics.image.PeakSignalNoiseRatio is not PeakSignalNoiseRatio  # the real package, not a stand-in
assert torch.equal(value, torchmetrics.image.PeakSignalNoiseRatio(data_range=1.0)(rendered, target))
"""

METRICS_CALLED_IN_NESTED_BLOCKS = """
import sys, torch
from votesplat_ns.ns import compat, patches
rendered, target = torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 8)
with patches.metrics_at_first_use():  # a launcher's, around votesplat's own in populate_modules
    with patches.metrics_at_first_use():
        from torchmetrics.image import PeakSignalNoiseRatio
        psnr = PeakSignalNoiseRatio(data_range=1.0)
    value = psnr(rendered, target)  # called while the outer block is open: the real package is imported
    assert type(psnr.built).__module__.startswith("torchmetrics."), type(psnr.built)
import torchmetrics.image
assert hasattr(torchmetrics, "Metric")  # the real package stayed
assert torch.equal(value, torchmetrics.image.PeakSignalNoiseRatio(data_range=1.0)(rendered, target))
"""


@pytest.mark.parametrize(
    "script", [METRICS_UNIMPORTED, METRICS_CALLED_IN_NESTED_BLOCKS], ids=["unimported", "called-in-nested-blocks"]
)
def test_metrics_at_first_use_leaves_torchmetrics_unimported_until_a_metric_is_called(script):
    """Where torchmetrics is not imported yet (every command's process), the block does not import it: stand-in
    modules serve splatfacto's two imports and leave sys.modules with the block; the first call imports the real
    package, and later imports get it, also when that call comes inside a block (blocks nested)."""
    result = subprocess.run([sys.executable, "-c", script], check=False, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]


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


RUN_LOADED = """
import sys
from votesplat_ns.ns.run import load_run
loaded = load_run(sys.argv[1])
assert loaded.scene.means.shape[0] > 0
assert not any(name.startswith("torchmetrics") for name in sys.modules), "loading a run imported torchmetrics"
"""


def test_loading_a_run_does_not_import_torchmetrics(trained_demo):
    """What ns-export, the viewer and votesplat's commands do first: the model they build holds splatfacto's metrics
    unbuilt, so the seconds of torchmetrics' import are not paid by commands that never call them."""
    result = subprocess.run(
        [sys.executable, "-c", RUN_LOADED, str(trained_demo)], check=False, capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr[-3000:]
