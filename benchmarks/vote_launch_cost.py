"""Host time of the fused vote step's parts, timed alone in a loop on CUDA (median microseconds).

    python benchmarks/vote_launch_cost.py        # on the GPU machine, after `bash scripts/gpu/run.sh setup`

Prints the whole step (draw, forward, backward through autograd), the training step's call (the backward at
once, ``accumulate_grad``) with the JIT's launches and with direct ones (``core/triton_launch.py``), the
forward alone, the draw, one zero fill and one allocation, and for each of the three kernel launches the full
``kernel[grid](...)``, the JIT's argument binding alone, the compiled kernel's runner (``compiled[grid]``) and
its launcher called directly; then a cProfile of the training step's call with direct launches. Inside a training step every one of these costs two to three
times as much (BENCHMARKS.md, "Training time"): compare parts here, not totals.
"""

from __future__ import annotations

import cProfile
import pstats
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from benchmarks.bench_vote_render import block_vote_maps, random_gaussians  # noqa: E402
from votesplat_ns.core import triton_launch, vote_fused, vote_kernel  # noqa: E402
from votesplat_ns.core.vote_render import VoteRenderOptions  # noqa: E402

WIDTH, HEIGHT, GAUSSIANS, LEVELS, PIXELS = 720, 540, 100_000, 2, 4096


def median_us(step, repeats: int = 1500) -> float:
    for _ in range(100):
        step()
    torch.cuda.synchronize()
    times = []
    for i in range(repeats):
        start = time.perf_counter_ns()
        step()
        times.append(time.perf_counter_ns() - start)
        if i % 50 == 49:  # keep the GPU's queue short: host time, not back-pressure
            torch.cuda.synchronize()
    torch.cuda.synchronize()
    return statistics.median(times) / 1e3


def main() -> int:
    if not torch.cuda.is_available():
        sys.exit("vote_launch_cost.py times CUDA launches; no CUDA device is visible, nothing was timed")
    import triton
    from gsplat import rasterization

    device = torch.device("cuda")
    print(f"torch {torch.__version__}, triton {triton.__version__}")
    scene = random_gaussians(GAUSSIANS, WIDTH, HEIGHT, 0, device, 0)
    with torch.no_grad():
        _, _, info = rasterization(
            scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"],
            scene["viewmat"][None], scene["K"][None], WIDTH, HEIGHT, sh_degree=0, packed=False,
        )  # fmt: skip
    labels, centroids, voting = block_vote_maps(WIDTH, HEIGHT, LEVELS, device)
    offsets = torch.zeros(GAUSSIANS, LEVELS, 3, device=device, requires_grad=True)
    counts = torch.zeros(GAUSSIANS, LEVELS, device=device)
    stamps = torch.full((GAUSSIANS, LEVELS), -1, dtype=torch.int32, device=device)
    generator = torch.Generator(device=device).manual_seed(0)
    options = VoteRenderOptions(backend="triton")
    step_count = [0]

    def losses(accumulate_grad=False):
        step_count[0] += 1
        sample = torch.randint(voting.numel(), (PIXELS,), device=device, generator=generator)
        return vote_fused.vote_losses_sampled(
            info["means2d"][0], info["conics"][0], info["opacities"][0], scene["means"], offsets,
            scene["viewmat"], scene["K"], sample, voting, labels, centroids, WIDTH, 1.0,
            info["isect_offsets"][0], info["flatten_ids"], info["tile_size"], options, (1.0, 0.1),
            (counts, stamps, step_count[0]), check_inputs=False, accumulate_grad=accumulate_grad,
        )  # fmt: skip

    def vote_step():
        losses()["total"].backward()
        offsets.grad = None

    def training_vote_step():  # the model's call: the backward at once, no autograd
        losses(accumulate_grad=True)
        offsets.grad = None

    def forward_only():
        with torch.no_grad():
            losses()

    launches = []
    launch = vote_kernel._launch

    def recording(kernel, grid, *args, **kwargs):
        launches.append((kernel, grid, args, kwargs))
        launch(kernel, grid, *args, **kwargs)

    vote_kernel._launch = recording
    vote_step()
    torch.cuda.synchronize()
    vote_kernel._launch = launch

    zeros_like = torch.zeros(GAUSSIANS, LEVELS, 3, device=device)
    print(f"vote step, forward and backward: {median_us(vote_step, 800):.1f} us")
    for direct in (False, True):
        triton_launch.DIRECT = direct
        print(
            f"training vote step (accumulate_grad), direct launches {direct}: {median_us(training_vote_step, 800):.1f} us"
        )
    triton_launch.DIRECT = False
    print(f"forward only (no grad): {median_us(forward_only, 800):.1f} us")
    draw = lambda: torch.randint(voting.numel(), (PIXELS,), device=device, generator=generator)  # noqa: E731
    print(f"pixel draw: {median_us(draw, 800):.1f} us")
    print(f"zeros_like [N, L, 3]: {median_us(lambda: torch.zeros_like(zeros_like), 800):.1f} us")
    print(f"empty [P, 8, L]: {median_us(lambda: torch.empty(PIXELS, 8, LEVELS, device=device), 800):.1f} us")
    for kernel, grid, args, kwargs in launches:
        full = median_us(lambda: kernel[grid](*args, **kwargs))
        binder = kernel.device_caches[torch.cuda.current_device()][-1]  # Triton 3.x: the argument binder last
        bind = median_us(lambda: binder(*args, **kwargs))
        print(
            f"{kernel.fn.__name__}: {len(args)} + {len(kwargs)} arguments, launch {full:.1f} us, binding {bind:.1f} us"
        )
        compiled = kernel[grid](*args, **kwargs)
        names = kernel.arg_names
        params = list(args) + [kwargs[name] for name in names[len(args) :]]
        runner = compiled[tuple(grid) + (1,) * (3 - len(grid))]
        print(f"  compiled[grid](*params): {median_us(lambda: runner(*params)):.1f} us")
        stream = torch.cuda.current_stream().cuda_stream
        run, function, packed = compiled.run, compiled.function, compiled.packed_metadata
        g = tuple(grid) + (1,) * (3 - len(grid))
        print(
            "  compiled.run(...):"
            f" {median_us(lambda: run(g[0], g[1], g[2], stream, function, packed, None, None, None, *params)):.1f} us"
        )

    triton_launch.DIRECT = True
    profiler = cProfile.Profile()
    profiler.enable()
    for i in range(500):
        training_vote_step()
        if i % 50 == 49:
            torch.cuda.synchronize()
    profiler.disable()
    torch.cuda.synchronize()
    pstats.Stats(profiler).sort_stats("tottime").print_stats(20)
    return 0


if __name__ == "__main__":
    sys.exit(main())
