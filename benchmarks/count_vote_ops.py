"""Counts the aten ops and host syncs of one vote step, per phase, on CPU.

The vote pass is launch-bound on a GPU: its cost is the number of kernels it launches and the
host synchronisations that stall the launch queue, not arithmetic. Neither needs a GPU to count:
every kernel is one aten op at the dispatcher, and every host sync is an op that reads a device
value on the host or sizes a tensor by device data. This script runs, on a small synthetic scene
and the torch backend:

  * ``render_votes_tiled`` + ``vote_losses``, forward and backward, as the model calls them
    (all levels in one call), once with the default CPU walk width and once with the GPU's
    default width (a one-step walk);
  * the model's vote step (``VoteSplatModel.vote_loss_terms`` + backward) on a CPU-built model
    with random Gaussians, unless ``--no-model``;

under :class:`OpCounter`, a ``TorchDispatchMode`` (it sees autograd's backward ops too) joined
with a ``TorchFunctionMode`` (it sees ``Tensor.tolist``, which reads a CPU tensor without an aten
op). Ops are attributed to a phase by the functions of ``core/vote_render.py`` on the Python
stack when they run. It prints a table of ops and syncs per phase, and the median wall time of
the forward + backward on CPU (one thread; a rough secondary figure: CPU time is not launch
time).

    python benchmarks/count_vote_ops.py [--levels 2 4] [--pixels 1024] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path
from typing import Callable, Dict, List, Optional

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# aten ops that read a device value on the host (on CUDA: wait for the queue) or whose output shape
# depends on device data (the same wait, to size the result).
SYNC_OPS = {
    "_local_scalar_dense",  # item(), int(), float(), bool() of a tensor
    "is_nonzero",
    "item",
    "equal",  # torch.equal returns a Python bool
    "allclose",
    "nonzero",
    "argwhere",
    "masked_select",
    "unique",
    "_unique",
    "_unique2",
    "unique_dim",
    "unique_consecutive",
}
# Tensor methods that read device values without an aten op on CPU.
SYNC_METHODS = {"tolist", "numpy", "cpu", "__array__"}
# Phase of an op by the innermost of these core/vote_render.py functions on the stack.
# ("checks" also holds the lookup of each pixel's tile run, _pixel_runs, which the walk needs.)
CHECK_FUNCTIONS = {
    "_validate_inputs",
    "_validate_tiles",
    "_finiteness_checks",
    "_all_finite",
    "_read_host",
    "_raise_unless",
    "_pixel_runs",
    "_use_kernel",
    "_requested_backend",
    "_check_render_inputs",
    "_check_loss_inputs",
}
WALK_FUNCTIONS = {"_tiled_members", "_run_entries"}
FINISH_FUNCTIONS = {"_finish"}
RENDER_FILE = "vote_render.py"
# Ops that only make a new view of existing memory: no kernel launch on a GPU.
VIEW_OPS = {
    "view",
    "_unsafe_view",
    "reshape",
    "select",
    "slice",
    "unsqueeze",
    "squeeze",
    "detach",
    "alias",
    "expand",
    "t",
    "transpose",
    "permute",
    "as_strided",
    "split",
    "unbind",
    "narrow",
    "diagonal",
    "lift_fresh",
}
# Ops that only allocate (the caching allocator, no kernel launch on a GPU).
ALLOC_OPS = {"empty", "empty_like", "empty_strided", "new_empty", "new_empty_strided"}
PHASES = ("model: sampling", "checks", "walk", "blend", "finish", "loss checks", "losses", "backward", "other")


def _is_sync(func, args) -> bool:
    name = func.__name__.split(".")[0]
    if name in SYNC_OPS:
        return True
    if name == "repeat_interleave":
        return len(args) < 1 or "output_size" not in str(args)  # conservative: only the Tensor overload syncs
    if name in ("index", "index_put", "index_put_", "_index_put_impl_"):
        indices = args[1] if len(args) > 1 else ()
        return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in indices if i is not None)
    return False


class _SyncMethods(TorchFunctionMode):
    """Tensor methods that read values on the host without an aten op on CPU (``tolist``)."""

    def __init__(self, owner: "OpCounter"):
        super().__init__()
        self.owner = owner

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", "")
        if name in SYNC_METHODS:
            self.owner._record_sync(name)
        return func(*args, **(kwargs or {}))


class OpCounter(TorchDispatchMode):
    """Counts aten ops and host syncs per phase of the vote step (see the module docstring).

    ``with OpCounter() as counter:``; ``counter.ops[phase]``, ``counter.syncs[phase]`` (a list of
    op names); ``with counter.phase("backward"):`` forces a phase.
    """

    def __init__(self) -> None:
        super().__init__()
        self.ops: Dict[str, int] = Counter()
        self.kernels: Dict[str, int] = Counter()
        self.op_names: Dict[str, Counter] = defaultdict(Counter)
        self.syncs: Dict[str, List[str]] = defaultdict(list)
        self.allocs = 0
        self.triton_launches = 0
        self.triton_names: Dict[str, int] = Counter()
        self._forced: Optional[str] = None
        self._walked = False
        self._methods = _SyncMethods(self)
        self._launch = None
        self._inside_launch = False

    def __enter__(self):
        super().__enter__()
        self._methods.__enter__()
        # Triton kernels are no aten ops: count them where the vote kernels launch (vote_kernel._launch)
        from votesplat_ns.core import vote_kernel

        self._launch = vote_kernel._launch

        def counted(kernel, grid, *args, **kwargs):
            self.triton_launches += 1
            self.triton_names[getattr(kernel, "__name__", str(kernel))] += 1
            assert self._launch is not None
            # Triton's CPU interpreter copies the arguments with torch ops: not the kernel's launches
            self._inside_launch = True
            try:
                return self._launch(kernel, grid, *args, **kwargs)
            finally:
                self._inside_launch = False

        vote_kernel._launch = counted
        return self

    def __exit__(self, *exc):
        from votesplat_ns.core import vote_kernel

        vote_kernel._launch = self._launch
        self._methods.__exit__(*exc)
        return super().__exit__(*exc)

    class _Phase:
        def __init__(self, counter: "OpCounter", name: str):
            self.counter, self.name = counter, name

        def __enter__(self):
            self.previous, self.counter._forced = self.counter._forced, self.name

        def __exit__(self, *exc):
            self.counter._forced = self.previous

    def phase(self, name: str) -> "OpCounter._Phase":
        return OpCounter._Phase(self, name)

    @property
    def total_ops(self) -> int:
        return sum(self.ops.values())

    @property
    def total_kernels(self) -> int:
        return sum(self.kernels.values())

    @property
    def total_syncs(self) -> int:
        return sum(len(v) for v in self.syncs.values())

    def _current_phase(self) -> str:
        if self._forced is not None:
            return self._forced
        frame = sys._getframe(2)
        names = []
        in_model = False
        while frame is not None:
            filename = frame.f_code.co_filename
            if filename.endswith(RENDER_FILE):
                names.append(frame.f_code.co_name)
            elif filename.endswith("model.py") and "votesplat_ns" in filename:
                in_model = True
            frame = frame.f_back
        if not names:
            return "model: sampling" if in_model else "other"
        if "vote_losses" in names:
            return "loss checks" if CHECK_FUNCTIONS.intersection(names) else "losses"
        if WALK_FUNCTIONS.intersection(names):
            self._walked = True
            return "walk"
        if CHECK_FUNCTIONS.intersection(names):
            return "checks"
        if FINISH_FUNCTIONS.intersection(names):
            return "finish"
        return "blend" if self._walked else "checks"

    def _record_sync(self, name: str) -> None:
        self.syncs[self._current_phase()].append(name)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if self._inside_launch:
            return func(*args, **(kwargs or {}))
        phase = self._current_phase()
        name = func.__name__
        self.ops[phase] += 1
        base = name.split(".")[0]
        self.kernels[phase] += base not in VIEW_OPS
        self.allocs += base in ALLOC_OPS
        self.op_names[phase][name] += 1
        if _is_sync(func, args):
            self.syncs[phase].append(name)
        return func(*args, **(kwargs or {}))


def launches(counter: OpCounter) -> int:
    """Kernel launches a GPU would make: aten ops that are neither views nor allocations, plus Triton kernels."""
    return counter.total_kernels - counter.allocs + counter.triton_launches


def launch_names(counter: OpCounter) -> Dict[str, int]:
    """The launching ops by name (aten and Triton), for messages."""
    names: Dict[str, int] = Counter()
    for per_phase in counter.op_names.values():
        for name, calls in per_phase.items():
            base = name.split(".")[0]
            if base not in VIEW_OPS and base not in ALLOC_OPS:
                names[name] += calls
    names.update(counter.triton_names)
    return dict(names)


def count_step(step: Callable[[], torch.Tensor]) -> OpCounter:
    """Runs ``step`` (forward, returns the loss) and its backward under an OpCounter."""
    with OpCounter() as counter:
        loss = step()
        with counter.phase("backward"):
            loss.backward()
    return counter


def median_ms(step: Callable[[], torch.Tensor], repeats: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        step().backward()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        step().backward()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times)


# ---------------------------------------------------------------------------- the renderer's vote step


def synthetic_scene(n: int, width: int, height: int, pixels: int, levels: int, seed: int = 0):
    """Random Gaussians in front of one camera, its projection and tile lists (our CPU rasteriser)."""
    from benchmarks.bench_vote_render import random_gaussians
    from votesplat_ns.core.rasterize_torch import rasterize_torch

    device = torch.device("cpu")
    scene = random_gaussians(n, width, height, 0, device, seed)
    with torch.no_grad():
        _, _, info = rasterize_torch(
            scene["means"],
            scene["quats"],
            scene["scales"],
            scene["opacities"],
            scene["colors"],
            scene["viewmat"][None],
            scene["K"][None],
            width,
            height,
            sh_degree=0,
            tile_size=16,
            packed=False,
        )
    g = torch.Generator().manual_seed(seed + 1)
    flat = torch.randint(0, width * height, (pixels,), generator=g)
    pixel_xy = torch.stack([flat % width, flat // width], dim=1).float() + 0.5
    target_xy = pixel_xy[:, None, :] + 5.0 * torch.randn(pixels, levels, 2, generator=g)
    valid = torch.rand(pixels, levels, generator=g) < 0.8
    offsets = torch.zeros(n, levels, 3, requires_grad=True)
    return scene, info, pixel_xy, target_xy, valid, offsets


def render_step(scene, info, pixel_xy, target_xy, valid, offsets, options, chunk):
    from votesplat_ns.core.vote_render import render_votes_tiled, vote_losses

    def step():
        votes = scene["means"].detach()[:, None, :] + offsets
        render = render_votes_tiled(
            info["means2d"][0],
            info["conics"][0],
            info["opacities"][0],
            info["depths"][0],
            votes,
            scene["viewmat"],
            scene["K"],
            pixel_xy,
            info["isect_offsets"][0],
            info["flatten_ids"],
            info["tile_size"],
            options,
            chunk=chunk,
        )
        losses = vote_losses(render, target_xy, valid, options)
        return losses["vote"].sum() + 0.05 * losses["distortion"].sum()

    return step


# ---------------------------------------------------------------------------- the model's vote step


def model_step(levels: int, n: int, width: int, height: int, pixels: int):
    """VoteSplatModel.vote_loss_terms on a CPU-built model with random Gaussians, after project_for_votes; the
    step's batch (host tensors, as the datamanager gives them) is ``step.batch``."""
    import warnings

    from nerfstudio.data.scene_box import SceneBox

    from votesplat_ns.core.vote_maps import label_tensor, voting_pixels
    from votesplat_ns.ns.model import VoteSplatModelConfig
    from votesplat_ns.ns.rasterizer import project_for_votes

    names = tuple(f"level{i}" for i in range(levels))
    config = VoteSplatModelConfig(
        vote_levels=names,
        random_init=True,
        num_random=n,
        random_scale=2.0,
        num_downscales=0,
        vote_pixels_per_step=pixels,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = config.setup(
            scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]])), num_train_data=1, metadata={}
        )
    model.train()
    model.step = 10_000
    focal = 0.8 * width
    K = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    viewmat = torch.eye(4)
    viewmat[2, 3] = 3.0
    with torch.no_grad():
        model.info = project_for_votes(
            model.means,
            model.quats,
            torch.exp(model.scales),
            torch.sigmoid(model.opacities).squeeze(-1),
            viewmat,
            K,
            width,
            height,
        )
    # Masks: a grid of rectangles per level (finer at later levels), label 0 = no mask on a border strip.
    labels = torch.zeros(levels, height, width, dtype=torch.int32)
    centroids = []
    for level in range(levels):
        cells = 2 + 2 * level
        ys = torch.arange(height)[:, None] * cells // height
        xs = torch.arange(width)[None, :] * cells // width
        labels[level] = (ys * cells + xs + 1).int()
        labels[level, :4] = 0
        table = torch.full((cells * cells + 1, 2), float("nan"))
        for label in range(1, cells * cells + 1):
            rows, cols = torch.nonzero(labels[level] == label, as_tuple=True)
            if len(rows):
                table[label] = torch.stack([cols.float().mean(), rows.float().mean()]).round()
        centroids.append(table)
    size = max(len(t) for t in centroids)
    centroids = torch.stack([torch.cat([t, torch.full((size - len(t), 2), float("nan"))]) for t in centroids])
    labels = label_tensor(labels.numpy())  # the datamanager's compact ids
    batch = {"vote_labels": labels, "vote_centroids": centroids, "vote_pixels": voting_pixels(labels, centroids)}

    def step(seed: Optional[int] = None):
        """The model's vote loss (vote + 0.05 distortion, the default weights); ``seed``: first restart the torch
        seed and the model's vote pixel draws there, as in a run seeded with it (the draws come from the model's
        own generator)."""
        if seed is not None:
            torch.manual_seed(seed)
            model._vote_pixel_generator = None  # made again at the next draw, from the seed
        model.gauss_params["vote_offsets"].grad = None
        loss, _terms = model.vote_loss_terms(batch)
        return loss

    step.batch = batch  # pyright: ignore[reportFunctionMemberAccess]
    return model, step


# ---------------------------------------------------------------------------- report


def table_row(label: str, counter: OpCounter) -> str:
    """Per phase: launching ops (all aten ops, views included) / host syncs."""
    cells = []
    for phase in PHASES:
        ops, kernels, syncs = (
            counter.ops.get(phase, 0),
            counter.kernels.get(phase, 0),
            len(counter.syncs.get(phase, [])),
        )
        cells.append("-" if ops == 0 and syncs == 0 else f"{kernels} ({ops}) / {syncs}")
    total = f"{counter.total_kernels} ({counter.total_ops}) / {counter.total_syncs}"
    return f"| {label} | " + " | ".join(cells) + f" | {total} |"


def summary(counter: OpCounter) -> Dict[str, object]:
    return {
        "ops": dict(counter.ops),
        "syncs": {k: list(v) for k, v in counter.syncs.items()},
        "kernels": dict(counter.kernels),
        "total_ops": counter.total_ops,
        "total_kernels": counter.total_kernels,
        "total_syncs": counter.total_syncs,
        "op_names": {k: dict(v) for k, v in counter.op_names.items()},
    }


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--num-gaussians", type=int, default=3000)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--pixels", type=int, default=1024)
    parser.add_argument("--levels", type=int, nargs="+", default=[2, 4])
    parser.add_argument("--distortion", default="l1_pixels", choices=["l1", "l1_pixels", "squared", "none"])
    parser.add_argument("--repeats", type=int, default=20, help="timed forward+backward repeats (0: no timing)")
    parser.add_argument("--no-model", action="store_true", help="skip the model's vote step")
    parser.add_argument("--detail", action="store_true", help="also print the aten op names per phase")
    parser.add_argument("--json", type=Path, help="write the counts (and times) here")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    torch.set_num_threads(1)
    from votesplat_ns.core.vote_render import AUTO_PAIRS_PER_STEP, VoteRenderOptions

    options = VoteRenderOptions(distortion=args.distortion, backend="torch")
    results = {}
    header = "| step | " + " | ".join(PHASES) + " | total |"
    lines = [header, "|" + " --- |" * (len(PHASES) + 2)]
    times = []
    for levels in args.levels:
        scene, info, pixel_xy, target_xy, valid, offsets = synthetic_scene(
            args.num_gaussians, args.width, args.height, args.pixels, levels
        )
        runs = torch.diff(
            torch.cat([info["isect_offsets"].reshape(-1).long(), torch.tensor([info["flatten_ids"].numel()])])
        )
        print(
            f"L={levels}: {args.num_gaussians} Gaussians at {args.width}x{args.height}, "
            f"{int((info['radii'][0] > 0).sum())} in view, tile runs mean {runs.float().mean():.0f} / max {int(runs.max())}"
        )
        for walk, chunk in (("CPU walk", None), ("GPU walk", max(32, AUTO_PAIRS_PER_STEP // args.pixels))):
            step = render_step(scene, info, pixel_xy, target_xy, valid, offsets, options, chunk)
            step().backward()  # warm-up (first-call imports and caches out of the count)
            counter = count_step(step)
            label = f"render+losses L={levels}, {walk}"
            lines.append(table_row(label, counter))
            results[label] = summary(counter)
            if args.repeats:
                ms = median_ms(step, args.repeats)
                results[label]["median_ms"] = ms
                times.append(f"{label}: {ms:.1f} ms")
            if args.detail:
                for phase, names in counter.op_names.items():
                    print(f"  {label} {phase}: {dict(names)}  syncs {counter.syncs.get(phase, [])}")
        if not args.no_model:
            from votesplat_ns.core import vote_render

            _, step = model_step(levels, args.num_gaussians, args.width, args.height, args.pixels)
            cpu_pairs = vote_render.AUTO_PAIRS_PER_STEP_CPU
            for walk, pairs in (("CPU walk", cpu_pairs), ("GPU walk", AUTO_PAIRS_PER_STEP)):
                # the model takes the default walk width of its device; "GPU walk" uses the GPU's
                vote_render.AUTO_PAIRS_PER_STEP_CPU = pairs
                try:
                    step(seed=0).backward()
                    counter = count_step(lambda: step(seed=0))
                    label = f"model vote step L={levels}, {walk}"
                    lines.append(table_row(label, counter))
                    results[label] = summary(counter)
                    if args.repeats:
                        ms = median_ms(step, args.repeats)
                        results[label]["median_ms"] = ms
                        times.append(f"{label}: {ms:.1f} ms")
                finally:
                    vote_render.AUTO_PAIRS_PER_STEP_CPU = cpu_pairs
                if args.detail:
                    for phase, names in counter.op_names.items():
                        print(f"  {label} {phase}: {dict(names)}  syncs {counter.syncs.get(phase, [])}")
    print(
        "\nlaunching aten ops (all aten ops, views included) / host syncs, per phase "
        f"(torch {torch.__version__}, CPU, backend torch, {args.distortion}):\n"
    )
    print("\n".join(lines))
    if times:
        print(f"\nforward+backward, CPU, 1 thread, median of {args.repeats}:")
        print("\n".join(times))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
