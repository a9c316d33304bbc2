"""Shared fixtures: one short CPU training run of votesplat on the bundled demo scene."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Dict, Optional, Sequence

import pytest
from preloaded_runner import PreloadedScripts

# The environment this test session started with, before what it imports sets variables of its own (cv2,
# sklearn, open3d and torch's compiler do): commands the tests start run under it, whichever tests ran before.
STARTED_ENV = dict(os.environ)
DEMO_SCENE = Path(__file__).resolve().parents[1] / "votesplat_ns" / "data" / "demo"
BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
BIN = Path(sys.executable).parent
# the console scripts the tests run (``preloaded`` keeps a runner of each)
CONSOLE_SCRIPTS = ("ns-train", "ns-export", "ns-viewer", "votesplat")
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


def command_env(home: Optional[Path] = None) -> Dict[str, str]:
    """The environment a console script runs under: the one this session started with (``STARTED_ENV``, not what
    this process's imports have set since), pytest's name of the running test, a wide console, and the home
    folder ``home``."""
    env = dict(STARTED_ENV, COLUMNS="200")
    if "PYTEST_CURRENT_TEST" in os.environ:
        env["PYTEST_CURRENT_TEST"] = os.environ["PYTEST_CURRENT_TEST"]
    if home is not None:
        env.update(HOME=str(home), XDG_CACHE_HOME=str(home / ".cache"), MPLCONFIGDIR=str(home / ".matplotlib"))
    return env


@pytest.fixture(scope="session")
def preloaded(tmp_path_factory):
    """The console scripts (``CONSOLE_SCRIPTS``), each imported once in a runner of its own that forks a process
    per command (tests/preloaded_runner.py), for the whole session. All four start together, so that their imports
    run side by side rather than each before its first command; a test that also needs ``trained_demo`` asks for
    it first, so that they do not slow its training. None (every command in a new interpreter) where CUDA is
    available: a child forked after something initialised CUDA cannot use it. VOTESPLAT_TEST_PRELOAD=0 also
    starts each command afresh."""
    import torch

    if os.environ.get("VOTESPLAT_TEST_PRELOAD", "1") == "0" or torch.cuda.is_available():
        yield None
        return
    scripts = PreloadedScripts(tmp_path_factory.mktemp("preloaded"))
    scripts.start([str(BIN / name) for name in CONSOLE_SCRIPTS], command_env())
    yield scripts
    scripts.close()
    if scripts.declined:  # each ran in a new interpreter instead, correct but slow: say which and why
        warnings.warn("commands not run preloaded: " + "; ".join(f"{argv}: {why}" for argv, why in scripts.declined))


def run_script(
    argv: Sequence[str],
    env: Dict[str, str],
    cwd: Path,
    preloaded: Optional[PreloadedScripts],
    timeout: float = 900,
    drop_capabilities: Sequence[int] = (),
    fresh_prefix: Sequence[str] = (),
) -> subprocess.CompletedProcess:
    """``subprocess.run(argv, env=env, cwd=cwd, timeout=timeout, capture_output=True, text=True)``: in a fork of
    the preloaded runner of ``argv[0]`` (a console script) where there is one that can run it, else in a new
    interpreter. ``drop_capabilities``: the fork runs without these capabilities, as ``fresh_prefix`` (setpriv)
    leaves the new interpreter (the runner checks that the capability sets are the same)."""
    if preloaded is not None:
        done = preloaded.run(argv, env, cwd, timeout=timeout, drop_capabilities=drop_capabilities)
        if done is not None:
            return done
    return subprocess.run(
        [*fresh_prefix, *argv], capture_output=True, check=False, text=True, cwd=cwd, timeout=timeout, env=env
    )


@pytest.fixture
def run_console_script(preloaded, tmp_path_factory):
    """``run_console_script(argv, cwd=None, timeout=600)``: what ``subprocess.run(argv, capture_output=True, text=True)``
    returns for the console script ``argv[0]`` (``BIN / name``), run under ``command_env`` with a new empty home
    folder (outside the test's ``tmp_path``) in ``cwd`` (default: this process's), through ``preloaded``'s
    runners."""

    def run(argv: Sequence[str], cwd: Optional[Path] = None, timeout: float = 600) -> subprocess.CompletedProcess:
        home = tmp_path_factory.mktemp("home")
        return run_script(argv, command_env(home), cwd or Path.cwd(), preloaded, timeout)

    return run


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
