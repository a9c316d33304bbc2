"""Shared fixtures: one short CPU training run of votesplat on the bundled demo scene."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

# The environment this test session started with, before what it imports sets variables of its own (cv2,
# sklearn, open3d and torch's compiler do): commands the tests start run under it, whichever tests ran before.
STARTED_ENV = dict(os.environ)
DEMO_SCENE = Path(__file__).resolve().parents[1] / "votesplat_ns" / "data" / "demo"
BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
# Short enough for CI on 2 cores, long enough for the votes to move well past their start.
DEMO_STEPS = int(os.environ.get("VOTESPLAT_TEST_STEPS", "240"))
DEMO_VOTE_START = 40
# Tests that use a fixture which trains are marked ``slow``; ``pytest -m "not slow"`` skips them.
TRAINING_FIXTURES = ("trained_demo", "plain_runs")


def pytest_collection_modifyitems(config, items) -> None:
    cases = {}  # per module with an INTERPRETER_CASES list: its names not collected
    for item in items:
        if any(name in TRAINING_FIXTURES for name in getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)
        module = getattr(item, "module", None)
        listed = getattr(module, "INTERPRETER_CASES", None)
        if listed is not None:
            left = cases.setdefault(module.__name__, set(listed))
            if item.name in listed:
                item.add_marker(pytest.mark.interpreter)
                left.discard(item.name)
    # a renamed test or parametrization must not drop out of the interpreter pass unseen (checked when whole
    # files are collected: this hook sees the items before -k and -m deselect any)
    if not any("::" in arg for arg in config.args):
        for module_name, left in cases.items():
            if left:
                raise pytest.UsageError(f"{module_name}.INTERPRETER_CASES names no collected test: {sorted(left)}")


def run_benchmark(script: str, *args: str, expect_ok: bool = True) -> subprocess.CompletedProcess:
    """``python benchmarks/<script> args...`` in a process of its own (benchmarks/ is no package the tests
    import); with ``expect_ok`` its exit status must be 0."""
    root = str(BENCHMARKS.parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))}
    done = subprocess.run(
        [sys.executable, str(BENCHMARKS / script), *args],
        check=False,
        capture_output=True,
        text=True,
        cwd=root,
        env=env,
    )
    if expect_ok:
        assert done.returncode == 0, done.stderr[-2000:]
    return done


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    """The bad-input probe's report (tests/test_bad_inputs.py ``Probe``), when its cases ran in this session."""
    probe = getattr(config, "votesplat_bad_input_probe", None)
    if probe is not None and probe.outcomes:
        terminalreporter.section("bad-input probe")
        for line in probe.summary():
            terminalreporter.write_line(line)


def train_votesplat(data: Path, output_dir: Path, steps: int, vote_start: int, **model_overrides) -> Path:
    """Train votesplat in-process on CPU and return the run's config.yml."""
    from votesplat_ns.ns.method import train_in_process

    # CPU budget: render at 64 px (splatfacto's resolution schedule stays at 1/2 for the whole
    # run) and sample 1024 vote pixels per step; the vote loss is a mean over masked pixels,
    # so fewer samples keep its expected gradient. A few hundred steps: vote on every one.
    cpu_budget = dict(
        num_downscales=1, resolution_schedule=100 * steps, vote_pixels_per_step=1024, vote_every_n_steps=1
    )
    return train_in_process(data, output_dir, steps, vote_start, "cpu", "test", **{**cpu_budget, **model_overrides})


@pytest.fixture(scope="session")
def trained_demo(tmp_path_factory) -> Path:
    """config.yml of a votesplat run on the bundled demo scene (CPU, a few hundred steps).

    VOTESPLAT_TRAINED_DEMO=<config.yml of an earlier run of this fixture> reuses that run
    (a local shortcut while iterating on tests; CI always trains).
    """
    reuse = os.environ.get("VOTESPLAT_TRAINED_DEMO")
    if reuse:
        return Path(reuse)
    output_dir = tmp_path_factory.mktemp("demo_run")
    return train_votesplat(DEMO_SCENE, output_dir, DEMO_STEPS, DEMO_VOTE_START)


@pytest.fixture
def one_torch_thread():
    """A model this small runs fastest on one thread; several threads oversubscribe a busy CI machine."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def assert_offsets_beat_zero(pipeline) -> None:
    """The trained vote offsets give a smaller vote error on training view 0 than zero offsets, at every level.

    Zeroes the model's offsets: call it last on a pipeline.
    """
    model, datamanager = pipeline.model, pipeline.datamanager
    camera = datamanager.train_dataset.cameras[0:1]
    batch = datamanager.vote_batch(0)
    trained = model.vote_pixel_error(camera, batch)
    model.gauss_params["vote_offsets"].data.zero_()
    untrained = model.vote_pixel_error(camera, batch)
    assert (trained < untrained).all(), (trained, untrained)
