"""Where a training step spends its host time: a profile of steps [A, B) of a running ``ns-train``.

Installed by ``scripts/gpu/run.sh``'s launcher when ``VOTESPLAT_PROFILE_STEPS=A:B`` is set (for either
method, so splatfacto and votesplat are profiled alike). Over those steps it records

* the wall time per step (CUDA synchronised at A and B, so the mean is real time per step),
* a ``torch.profiler`` table: the named phases below (``record_function`` around nerfstudio's and our
  methods) and the torch ops by self CPU time, with CUDA kernel time and launch counts,
* every operation that synchronises the host with the GPU (``torch.cuda.set_sync_debug_mode``),
  counted per call site (the innermost frames of the project, nerfstudio and gsplat).

Written to ``$VOTESPLAT_PROFILE_OUT`` (default ``train_profile.txt``), the profiler's timeline beside it
(``<name>_trace.json``, Chrome's trace format). Timing inside the window is
perturbed by the profiler; the per-step wall time is measured on the steps before it.

``install_capture`` (run.sh: ``VOTESPLAT_CAPTURE_VOTE_STEP=N``) saves the arguments of the first fused vote
step at or after step N (``vote_losses_sampled``'s tensors on the CPU, its other arguments as values), so
``benchmarks/bench_captured_step.py`` can time the vote kernels on a trained, densified scene's real inputs.

``install_step_times`` (run.sh: ``VOTESPLAT_STEP_TIMES=1``) instead times a whole run without the
profiler: for every step its wall time (from one step's start to the next one's) and the host time
of each phase above (``VOTESPLAT_STEP_TIMES=walls``: not the phases, whose wrappers would time them), plus the set-up before step 0 and the tail after the last step's iteration
(the final callbacks, e.g. votesplat's foreground pass, and the checkpoint). The host and
the GPU run in lock step in these trainings (splatfacto reads the GPU ~15 times a step), so a
phase's host time includes the GPU work it waits for.
"""

from __future__ import annotations

import atexit
import collections
import importlib
import json
import os
import time
import traceback
import warnings
from typing import Callable, Dict, List

import torch
from nerfstudio.engine.trainer import Trainer

# (module, class, method): the phases of a step, as nerfstudio 1.1.5 calls them
PHASES = (
    ("nerfstudio.engine.trainer", "Trainer", "train_iteration"),
    ("nerfstudio.pipelines.base_pipeline", "VanillaPipeline", "get_train_loss_dict"),
    ("nerfstudio.data.datamanagers.full_images_datamanager", "FullImageDatamanager", "next_train"),
    ("nerfstudio.models.splatfacto", "SplatfactoModel", "get_outputs"),
    ("nerfstudio.models.splatfacto", "SplatfactoModel", "get_loss_dict"),
    ("nerfstudio.models.splatfacto", "SplatfactoModel", "get_metrics_dict"),
    ("nerfstudio.models.splatfacto", "SplatfactoModel", "step_post_backward"),
    ("nerfstudio.engine.optimizers", "Optimizers", "optimizer_scaler_step_some"),
    ("nerfstudio.engine.optimizers", "Optimizers", "zero_grad_some"),
    ("torch.autograd", None, "backward"),
    ("nerfstudio.engine.optimizers", "Optimizers", "scheduler_step_all"),
    ("votesplat_ns.ns.datamanager", "VoteDataManager", "kept_vote_batch"),
    ("votesplat_ns.ns.model", "VoteSplatModel", "get_outputs"),
    ("votesplat_ns.ns.model", "VoteSplatModel", "get_metrics_dict"),
    ("votesplat_ns.ns.model", "VoteSplatModel", "get_loss_dict"),
    ("votesplat_ns.ns.model", "VoteSplatModel", "step_post_backward"),
    ("votesplat_ns.ns.model", "VoteSplatModel", "vote_loss_terms"),
    ("votesplat_ns.ns.model", "VoteSplatModel", "record_vote_support"),
    ("votesplat_ns.core.vote_fused", None, "vote_losses_tiled"),
    # the parts of a fused vote step (vote_loss_terms' remainder is the draw and the model's own code)
    ("votesplat_ns.ns.model", "VoteSplatModel", "_vote_maps"),
    ("votesplat_ns.ns.model", "VoteSplatModel", "_support_in_backward"),
    ("votesplat_ns.core.vote_fused", None, "vote_losses_sampled"),
    ("votesplat_ns.core.vote_fused", "_FusedVoteLosses", "forward"),
    ("votesplat_ns.core.vote_fused", "_FusedVoteLosses", "backward"),
    ("votesplat_ns.core.vote_kernel", None, "_launch"),
)
SYNC_SITE_FRAMES = 3


def _wrap(function: Callable, label: str) -> Callable:
    def wrapped(*args, **kwargs):
        with torch.profiler.record_function(label):
            return function(*args, **kwargs)

    wrapped.__wrapped__ = function  # type: ignore[attr-defined]
    return wrapped


def _timed(function: Callable, label: str, totals: Dict[str, float]) -> Callable:
    def wrapped(*args, **kwargs):
        start = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            totals[label] = totals.get(label, 0.0) + time.perf_counter() - start

    wrapped.__wrapped__ = function  # type: ignore[attr-defined]
    return wrapped


def _install_phases(wrap: Callable[[Callable, str], Callable] = _wrap) -> None:
    for module_name, class_name, name in PHASES:
        module = importlib.import_module(module_name)
        owner = getattr(module, class_name) if class_name else module
        label = f"## {class_name or module_name.rsplit('.', 1)[-1]}.{name}"
        wrapped = wrap(getattr(owner, name), label)
        # an autograd Function's forward and backward are static methods: kept static
        static = class_name is not None and isinstance(vars(owner).get(name), staticmethod)
        setattr(owner, name, staticmethod(wrapped) if static else wrapped)
        if class_name is None:  # a module function: rebind it where the model imported it
            model = importlib.import_module("votesplat_ns.ns.model")
            if hasattr(model, name):
                setattr(model, name, getattr(owner, name))


def _sync_site() -> str:
    frames = [f for f in traceback.extract_stack()[:-2] if "/torch/" not in f.filename and "warnings" not in f.filename]
    ours = [f for f in frames if any(k in f.filename for k in ("votesplat_ns", "nerfstudio", "gsplat"))]
    return " <- ".join(f"{os.path.basename(f.filename)}:{f.lineno} {f.name}" for f in ours[-SYNC_SITE_FRAMES:][::-1])


def _synchronize() -> None:
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize()


def install(first: int, stop: int, out_path: str) -> None:
    """Profile ns-train's steps [first, stop) (call before nerfstudio's trainer starts)."""
    _install_phases()
    original = Trainer.train_iteration
    state: Dict = {"syncs": collections.Counter(), "times": []}
    shown = warnings.showwarning

    def on_warning(message, category, filename, lineno, file=None, line=None):
        if "synchronizing" in str(message):
            state["syncs"][_sync_site()] += 1
            return
        shown(message, category, filename, lineno, file, line)

    def train_iteration(self, step):
        if step == first - 20:
            _synchronize()
            state["t_before"] = time.perf_counter()
        if step == first:
            _synchronize()
            state["wall_before"] = (time.perf_counter() - state["t_before"]) / 20 if "t_before" in state else None
            state["profiler"] = torch.profiler.profile(
                activities=[torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
            )
            state["profiler"].__enter__()
            warnings.showwarning = on_warning
            warnings.simplefilter("always")
            if torch.cuda.is_available():
                torch.cuda.set_sync_debug_mode("warn")
            state["t0"] = time.perf_counter()
        result = original(self, step)
        if step == stop - 1:
            if torch.cuda.is_available():
                torch.cuda.set_sync_debug_mode(0)
            _synchronize()
            elapsed = time.perf_counter() - state["t0"]
            warnings.showwarning = shown
            state["profiler"].__exit__(None, None, None)
            _write(out_path, state, first, stop, elapsed, type(self.pipeline.model).__name__)
        return result

    Trainer.train_iteration = train_iteration


def install_step_times(out_path: str, phases: bool = True) -> None:
    """Time every step of ns-train and its phases (host time, no profiler) into ``out_path`` (JSON). Without
    ``phases`` only the steps: the phases' wrappers cost each call a few microseconds, and votesplat has more of
    them (its vote losses' parts), which would charge a comparison of the methods' walls to votesplat."""
    process_start = time.perf_counter()
    phase_totals: Dict[str, float] = {}
    if phases:
        _install_phases(lambda function, label: _timed(function, label[3:], phase_totals))
    original = Trainer.train_iteration
    record: Dict = {"steps": [], "wall_ms": [], "phases_ms": collections.defaultdict(list)}
    state: Dict = {}

    def close_step(now: float) -> None:
        if "step" in state:
            record["steps"].append(state["step"])
            record["wall_ms"].append(round((now - state["start"]) * 1e3, 3))
            for label in phase_totals.keys() | record["phases_ms"].keys():
                values = record["phases_ms"][label]
                values.extend([0.0] * (len(record["steps"]) - 1 - len(values)))
                values.append(round(phase_totals.get(label, 0.0) * 1e3, 3))
        phase_totals.clear()

    def train_iteration(self, step):
        now = time.perf_counter()
        if "step" not in state:
            record["setup_s"] = round(now - process_start, 3)
        close_step(now)
        state.update(step=step, start=now)
        result = original(self, step)
        state["end"] = time.perf_counter()
        return result

    def write() -> None:
        now = time.perf_counter()
        if "end" in state:  # the last step ends with its iteration; what follows is the tail
            close_step(state["end"])
            record["tail_s"] = round(now - state["end"], 3)
        record["total_s"] = round(now - process_start, 3)
        record["phases_ms"] = dict(record["phases_ms"])
        with open(out_path, "w") as handle:
            json.dump(record, handle)

    Trainer.train_iteration = train_iteration
    atexit.register(write)


def _write(out_path: str, state: Dict, first: int, stop: int, elapsed: float, model_name: str) -> None:
    steps = stop - first
    events = state["profiler"].key_averages()
    lines: List[str] = [
        f"{model_name}: steps [{first}, {stop}) profiled",
        f"wall per step before the window (20 steps, synchronised): {state['wall_before'] * 1e3:.2f} ms"
        if state.get("wall_before")
        else "wall per step before: n/a",
        f"wall per step in the window (profiler on): {elapsed / steps * 1e3:.2f} ms",
        "",
        "phases (per step; CPU total includes children):",
    ]
    for event in sorted(events, key=lambda e: -e.cpu_time_total):
        if event.key.startswith("## "):
            lines.append(
                f"  {event.key[3:]:<45} calls {event.count / steps:6.2f}  cpu {event.cpu_time_total / steps / 1e3:7.3f} ms"
            )
    kernels = [e for e in events if e.device_type == torch.autograd.DeviceType.CUDA]
    kernel_ms = sum(e.self_device_time_total for e in kernels) / steps / 1e3
    launches = sum(e.count for e in kernels) / steps
    lines += ["", f"GPU kernels per step: {kernel_ms:.3f} ms in {launches:.1f} launches", ""]
    lines.append("syncs per step by call site:")
    for site, count in state["syncs"].most_common(25):
        lines.append(f"  {count / steps:6.2f}  {site}")
    lines += ["", "ops by self CPU time (top 40):"]
    lines.append(events.table(sort_by="self_cpu_time_total", row_limit=40, max_name_column_width=60))
    # GPU kernels by their own time: the vote kernels' share of a step (the host reads wait for it)
    kernels = [e for e in events if e.device_type == torch.autograd.DeviceType.CUDA and e.self_device_time_total > 0]
    kernels.sort(key=lambda e: -e.self_device_time_total)
    lines += ["", "GPU kernels by time (top 25; per step):"]
    for event in kernels[:25]:
        per_step_ms = event.self_device_time_total / 1e3 / steps
        lines.append(f"  {per_step_ms:8.3f} ms  {event.count / steps:6.2f}x  {event.key[:100]}")
    text = "\n".join(lines) + "\n"
    with open(out_path, "w") as handle:
        handle.write(text)
    # the timeline: where the host waits for the GPU, step by step
    state["profiler"].export_chrome_trace(os.path.splitext(out_path)[0] + "_trace.json")


def install_capture(step: int, out_path: str) -> None:
    """Save the arguments of the first fused vote step at or after ``step`` to ``out_path`` (torch.save), by
    ``vote_losses_sampled``'s parameter names: tensors on the CPU, the options as a dict, the support as its shape
    (the replay starts its own counts). The step is the one the model passes with the support counts."""
    import dataclasses
    import inspect

    model = importlib.import_module("votesplat_ns.ns.model")
    original_call = model.vote_losses_sampled
    signature = inspect.signature(original_call)
    done = False

    def vote_losses_sampled(*args, **kwargs):
        nonlocal done
        if done:
            return original_call(*args, **kwargs)
        arguments = signature.bind(*args, **kwargs).arguments
        support = arguments.get("support")
        if support is not None and support[2] >= step:
            record = {"step": support[2]}
            for name, value in arguments.items():
                if isinstance(value, torch.Tensor):
                    record[name] = value.detach().cpu().clone()
                elif name == "options":
                    record[name] = dataclasses.asdict(value)
                elif name == "support":
                    record[name] = tuple(value[0].shape)
                else:
                    record[name] = value
            torch.save(record, out_path)
            done = True
        return original_call(*args, **kwargs)

    model.vote_losses_sampled = vote_losses_sampled
