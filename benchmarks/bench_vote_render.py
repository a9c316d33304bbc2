"""Cost of the vote pass next to the RGB pass it rides on.

Times, on random Gaussians seen by one camera:
  * RGB: gsplat 1.4 ``rasterization`` forward + backward of a full image
    (what splatfacto pays per step);
  * vote: ``render_votes_tiled`` + ``vote_losses`` forward + backward on S
    sampled pixels, reusing the projection and tile lists of a rasterization
    (as the model does: geometry comes from the RGB pass's info), for L mask
    levels: L = 1 with [N, 3] votes, L > 1 with [N, L, 3] votes in one call
    (one walk, every level blended over it) and, for comparison, as L
    separate single-level calls; with each backend of ``--backends``: "torch", the torch code;
    "triton-fused": ``votesplat_ns.core.vote_fused.vote_losses_tiled``, the render and the losses
    in three Triton launches; "triton-sampled": ``vote_fused.vote_losses_sampled``, what a
    training step runs on CUDA with the default switches: the pixels drawn (one ``randint``) among
    the voting pixels of block-shaped vote maps and looked up in the forward kernel ([N, L, 3]
    votes at every L). The Triton ones once per ``--kernel-configs`` block width x warps.
Prints a markdown table of median milliseconds, peak extra GPU memory, both
also as a ratio to the RGB pass, and per step the host reads
(device-to-host syncs) and torch calls made from Python in the forward pass
(each call is one or more kernel launches). For the Triton kernels it first
prints the first call's wall time with an empty Triton cache (JIT
compilation of the forward and backward kernels: their "build time").

    python benchmarks/bench_vote_render.py --num-gaussians 500000 --width 1440 --height 1080 --pixels 4096 16384

``--device cpu`` runs the same passes with the pure-torch rasteriser, to
check the script (and count calls) without a GPU; use small sizes there.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, List, Optional, Tuple

import torch
from torch.overrides import TorchFunctionMode

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


TRITON_BACKENDS = ("triton-fused", "triton-sampled")


def chunk_arg(value: str) -> Optional[int]:
    return None if value == "auto" else int(value)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--num-gaussians", type=int, default=500_000)
    parser.add_argument("--width", type=int, default=1440)
    parser.add_argument("--height", type=int, default=1080)
    parser.add_argument(
        "--pixels", type=int, nargs="+", default=[4096, 16384], help="sampled pixels S for the vote pass"
    )
    parser.add_argument(
        "--chunks",
        type=chunk_arg,
        nargs="+",
        default=[None],
        help="render_votes_tiled chunk sizes to time ('auto' = the default, chunk=None)",
    )
    parser.add_argument("--levels", type=int, nargs="+", default=[1, 2, 4], help="mask levels L of the vote pass")
    parser.add_argument(
        "--backends",
        nargs="+",
        choices=["torch", *TRITON_BACKENDS],
        default=["torch", *TRITON_BACKENDS],
        help="vote pass implementations to time (torch: render_votes_tiled + vote_losses; triton-fused: "
        "vote_fused.vote_losses_tiled, render and losses fused; triton-sampled: vote_fused.vote_losses_sampled, "
        "the training step's path); the triton ones need CUDA",
    )
    parser.add_argument(
        "--kernel-configs",
        nargs="+",
        default=["32x2"],
        help="Triton kernel BLOCKxNUM_WARPS variants to time (walk block width x warps per program)",
    )
    parser.add_argument(
        "--distortion",
        default="l1_pixels",
        choices=["l1", "l1_pixels", "squared", "none"],
        help="VoteRenderOptions.distortion of the vote pass (the model's default: l1_pixels)",
    )
    parser.add_argument("--sh-degree", type=int, default=3)
    parser.add_argument("--tile-size", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--profile",
        action="store_true",
        help="also profile each timed vote step (torch.profiler, 5 steps): GPU kernel time and launches per step "
        "against the wall time, and the kernels that take the most GPU time",
    )
    parser.add_argument(
        "--host-profile",
        action="store_true",
        help="also run each timed Triton vote step 200 times under cProfile and print the Python functions "
        "with the most own time per step: where the host time between the kernels goes",
    )
    parser.add_argument(
        "--device", choices=["cuda", "cpu"], default="cuda", help="cpu: pure-torch rasteriser, for checking the script"
    )
    return parser.parse_args(argv)


def random_gaussians(n: int, width: int, height: int, sh_degree: int, device: torch.device, seed: int):
    """Gaussians filling the frustum of a camera at the origin looking down +z, 0.5-8 px across."""
    g = torch.Generator(device=device).manual_seed(seed)
    focal = 0.8 * width
    K = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]], device=device)
    viewmat = torch.eye(4, device=device)
    depth = 2.0 + 6.0 * torch.rand(n, generator=g, device=device)
    u = (torch.rand(n, generator=g, device=device) * 1.2 - 0.1) * width
    v = (torch.rand(n, generator=g, device=device) * 1.2 - 0.1) * height
    means = torch.stack([(u - width / 2) / focal * depth, (v - height / 2) / focal * depth, depth], dim=1)
    pixel_size = torch.exp(torch.empty(n, 3, device=device).uniform_(math.log(0.5), math.log(8.0), generator=g))
    scales = pixel_size * depth[:, None] / focal
    quats = torch.randn(n, 4, generator=g, device=device)
    opacities = 0.05 + 0.95 * torch.rand(n, generator=g, device=device)
    colors = 0.3 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, device=device)
    return dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmat=viewmat, K=K)


def measure(step: Callable[[], None], warmup: int, repeats: int, device: torch.device) -> Tuple[float, Optional[float]]:
    """Median milliseconds and, on CUDA, peak memory above the starting allocation (MiB)."""
    cuda = device.type == "cuda"
    for _ in range(warmup):
        step()
    if cuda:
        torch.cuda.synchronize()
        base = torch.cuda.memory_allocated()
        torch.cuda.reset_peak_memory_stats()
    times: List[float] = []
    for _ in range(repeats):
        if cuda:
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            step()
            end.record()
            torch.cuda.synchronize()
            times.append(start.elapsed_time(end))
        else:
            start_s = time.perf_counter()
            step()
            times.append((time.perf_counter() - start_s) * 1e3)
    peak = (torch.cuda.max_memory_allocated() - base) / 2**20 if cuda else None
    return statistics.median(times), peak


class CallCounter(TorchFunctionMode):
    """Torch calls made from Python, and those among them that read device values on the host."""

    HOST_READS = {"tolist", "item", "__bool__", "__int__", "__float__", "__index__", "cpu", "numpy", "nonzero"}

    def __init__(self):
        super().__init__()
        self.calls = 0
        self.host_reads = 0

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        self.calls += 1
        if name in self.HOST_READS:
            self.host_reads += 1
        elif name in ("__getitem__", "__setitem__"):
            index = args[1] if isinstance(args[1], tuple) else (args[1],)
            self.host_reads += any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in index)
        return func(*args, **kwargs)


def main(argv=None) -> int:
    args = parse_args(argv)
    cache = None
    triton_backends = set(TRITON_BACKENDS).intersection(args.backends)
    if args.device == "cuda" and triton_backends and "TRITON_CACHE_DIR" not in os.environ:
        # an empty Triton cache, so the first call's time is the kernels' full JIT build
        from votesplat_ns.core.ply_io import make_temp_dir

        cache = make_temp_dir(Path(tempfile.gettempdir()) / "votesplat_triton_cache", "bench")
        os.environ["TRITON_CACHE_DIR"] = str(cache)
    try:
        return _run(args)
    finally:
        if cache is not None:
            shutil.rmtree(cache, ignore_errors=True)
            del os.environ["TRITON_CACHE_DIR"]


def _run(args: argparse.Namespace) -> int:
    device = torch.device(args.device)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            sys.exit(
                "bench_vote_render.py needs a CUDA GPU (gsplat's rasterizer is CUDA-only); none is visible, "
                "nothing was timed. --device cpu checks the script with the pure-torch rasteriser."
            )
        from gsplat import rasterization
    else:
        from votesplat_ns.core.rasterize_torch import rasterize_torch as rasterization

    from votesplat_ns.core import vote_kernel
    from votesplat_ns.core.vote_fused import vote_losses_sampled, vote_losses_tiled
    from votesplat_ns.core.vote_render import VoteRenderOptions, render_votes_tiled, vote_losses

    backends = list(args.backends)
    for backend in TRITON_BACKENDS:
        if backend in backends and vote_kernel.unavailable_reason(device) is not None:
            print(f"skipping the {backend} backend: {vote_kernel.unavailable_reason(device)}")
            backends.remove(backend)
    variants = [("torch", None)] if "torch" in backends else []
    for backend in TRITON_BACKENDS:
        if backend not in backends:
            continue
        for config in args.kernel_configs:
            try:
                block, warps = (int(x) for x in config.lower().split("x"))
            except ValueError:
                sys.exit(f"--kernel-configs: {config!r} is not BLOCKxWARPS (e.g. 32x2)")
            variants.append((backend, (block, warps)))

    scene = random_gaussians(args.num_gaussians, args.width, args.height, args.sh_degree, device, args.seed)
    params = {k: scene[k].clone().requires_grad_() for k in ("means", "quats", "scales", "opacities", "colors")}
    viewmat, K = scene["viewmat"], scene["K"]
    target_image = torch.rand(args.height, args.width, 3, device=device)

    def rasterize():
        return rasterization(
            params["means"],
            params["quats"],
            params["scales"],
            params["opacities"],
            params["colors"],
            viewmat[None],
            K[None],
            args.width,
            args.height,
            sh_degree=args.sh_degree,
            tile_size=args.tile_size,
            packed=False,
        )

    def rgb_step():
        image, _, _ = rasterize()
        (image[0] - target_image).abs().mean().backward()

    rgb_ms, rgb_mib = measure(rgb_step, args.warmup, args.repeats, device)

    with torch.no_grad():
        _, _, info = rasterize()
    host_profiles = []
    max_levels = max(args.levels)
    vote_maps = {levels: block_vote_maps(args.width, args.height, levels, device) for levels in args.levels}
    # one offsets leaf per level count, as a model of that many levels has (a slice of one [N, 4, 3] leaf
    # would add the slice's backward, a zero fill and a copy, to the timed step)
    level_offsets = {
        levels: torch.zeros(args.num_gaussians, levels, 3, device=device, requires_grad=True) for levels in args.levels
    }
    rows = []
    compile_rows = []
    profiles = []
    cache_dir = os.environ.get("TRITON_CACHE_DIR")
    cache_was_empty = cache_dir is not None and not any(Path(cache_dir).iterdir())
    for pixels in args.pixels:
        g = torch.Generator(device=device).manual_seed(args.seed + 1)
        flat = torch.randint(0, args.width * args.height, (pixels,), generator=g, device=device)
        pixel_xy = torch.stack([flat % args.width, flat // args.width], dim=1).float() + 0.5
        target_xy = pixel_xy[:, None, :] + 20.0 * torch.randn(pixels, max_levels, 2, generator=g, device=device)
        # a pixel carries a 2D vote at some levels and not others, as with nested SAM masks
        valid = torch.rand(pixels, max_levels, generator=g, device=device) < 0.8
        runs = [
            (backend, config, chunk)
            for backend, config in variants
            for chunk in (args.chunks if backend == "torch" else ["-"])
        ]
        for backend, config, chunk in runs:
            fused = backend in TRITON_BACKENDS
            options = VoteRenderOptions(distortion=args.distortion, backend="triton" if fused else "torch")
            if config is not None:
                vote_kernel.BLOCK, vote_kernel.NUM_WARPS = config
            backend_label = backend if config is None else f"{backend} {config[0]}x{config[1]}"

            def vote_forward(votes: torch.Tensor):
                return render_votes_tiled(
                    info["means2d"][0],
                    info["conics"][0],
                    info["opacities"][0],
                    info["depths"][0],
                    votes,
                    viewmat,
                    K,
                    pixel_xy,
                    info["isect_offsets"][0],
                    info["flatten_ids"],
                    info["tile_size"],
                    options,
                    chunk=None if chunk == "-" else chunk,
                )

            with torch.no_grad():
                count = vote_forward(params["means"]).count.float()
            count_stats = (count.mean().item(), int(count.max().item()))
            for levels in args.levels:

                def one_call_step(levels=levels):
                    geometry = (info["means2d"][0], info["conics"][0], info["opacities"][0])
                    tiles = (info["isect_offsets"][0], info["flatten_ids"], info["tile_size"], options)
                    single = levels == 1 and backend != "triton-sampled"  # the sampled losses take [N, L, 3] only
                    offsets = level_offsets[levels]
                    means = params["means"].detach()
                    if backend == "triton-sampled":  # the training step: draw, then look up in the kernel
                        labels, centroids, voting = vote_maps[levels]
                        sample = torch.randint(voting.numel(), (pixels,), device=device, generator=g)
                        maps = (sample, voting, labels, centroids, args.width, 1.0)
                        losses = vote_losses_sampled(*geometry, means, offsets, viewmat, K, *maps, *tiles, (1.0, 0.1))
                        losses["total"].backward()
                        return
                    votes = means + offsets[:, 0] if single else means[:, None, :] + offsets
                    target = target_xy[:, 0] if single else target_xy[:, :levels]
                    mask = valid[:, 0] if single else valid[:, :levels]
                    if fused:
                        losses = vote_losses_tiled(*geometry, votes, viewmat, K, pixel_xy, target, mask, *tiles)
                    else:
                        losses = vote_losses(vote_forward(votes), target, mask, options, check_inputs=False)
                    (losses["vote"].sum() + 0.1 * losses["distortion"].sum()).backward()

                def separate_calls_step(levels=levels):
                    total = 0.0
                    offsets = level_offsets[levels]
                    for level in range(levels):
                        votes = params["means"].detach() + offsets[:, level]
                        losses = vote_losses(
                            vote_forward(votes), target_xy[:, level], valid[:, level], options, check_inputs=False
                        )
                        total = total + losses["vote"] + 0.1 * losses["distortion"]
                    total.backward()

                if levels == 1 and backend != "triton-sampled":
                    steps = [("votes [N,3]", one_call_step)]
                else:
                    steps = [("votes [N,L,3], one call", one_call_step)]
                    if backend == "torch":
                        steps.append(("votes [N,3], one call per level", separate_calls_step))
                for label, step in steps:
                    if backend != "torch" and device.type == "cuda":
                        # the first call of a new (levels, switches, block) combination JIT-compiles
                        torch.cuda.synchronize()
                        start_s = time.perf_counter()
                        step()
                        torch.cuda.synchronize()
                        compile_rows.append((backend_label, levels, pixels, time.perf_counter() - start_s))
                    ms, mib = measure(step, args.warmup, args.repeats, device)
                    if args.profile:
                        profiles.append((f"{backend_label}: {label}", levels, pixels, ms, profile_step(step, device)))
                    if args.host_profile and backend != "torch":
                        host_profiles.append((f"{backend_label}: {label}", levels, pixels, host_profile(step, device)))
                    with CallCounter() as counter:
                        step()
                    counts = (counter.host_reads, counter.calls)
                    rows.append((f"{backend_label}: {label}", levels, pixels, chunk, ms, mib) + counts + count_stats)

    run_starts = info["isect_offsets"][0].reshape(-1).long()
    runs = torch.diff(torch.cat([run_starts, run_starts.new_tensor([info["flatten_ids"].numel()])])).float()
    device_name = torch.cuda.get_device_name() if device.type == "cuda" else "CPU"
    print(
        f"\n{device_name}, torch {torch.__version__}; {args.num_gaussians} Gaussians at "
        f"{args.width}x{args.height}, SH degree {args.sh_degree}, tile {args.tile_size}; "
        f"{int((info['radii'][0] > 0).sum())} in view, tile runs mean {runs.mean():.0f} / max {runs.max():.0f}; "
        f"median of {args.repeats}; vote distortion {args.distortion}\n"
    )
    if compile_rows:
        cache_note = "an empty cache" if cache_was_empty else f"TRITON_CACHE_DIR={os.environ.get('TRITON_CACHE_DIR')}"
        print(f"First call of each Triton variant (JIT compilation; the first row started from {cache_note}):\n")
        print("| kernels | levels | pixels | first call s |")
        print("| --- | --- | --- | --- |")
        for label, levels, pixels, seconds in compile_rows:
            print(f"| {label} | {levels} | {pixels} | {seconds:.2f} |")
        print()
    print(
        "| pass | levels | pixels | chunk | fwd+bwd ms | x RGB time | peak extra MiB | x RGB memory | host reads "
        "| torch calls (fwd) | mean \\|M\\| | max \\|M\\| |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    print(
        f"| RGB rasterization | - | {args.width * args.height} | - | {rgb_ms:.2f} | 1 | {_mib(rgb_mib)} | 1 "
        f"| - | - | - | - |"
    )
    for label, levels, pixels, chunk, ms, mib, reads, calls, mean_count, max_count in rows:
        memory_ratio = "-" if mib is None or not rgb_mib else f"{mib / rgb_mib:.2f}"
        print(
            f"| {label} | {levels} | {pixels} | {'auto' if chunk is None else chunk} | {ms:.2f} | {ms / rgb_ms:.2f} "
            f"| {_mib(mib)} | {memory_ratio} | {reads} | {calls} | {mean_count:.1f} | {max_count} |"
        )
    for label, levels, pixels, (step_us, top) in host_profiles:
        print(
            f"\nhost profile of {label}, {levels} levels, {pixels} px: {step_us:.0f} us per step of Python; own time:"
        )
        for name, us, calls in top:
            print(f"  {us:7.1f} us  {calls:5.1f}x  {name}")
    for label, levels, pixels, ms, (kernel_ms, launches, top) in profiles:
        print(
            f"\nprofile of {label}, {levels} levels, {pixels} px: wall {ms:.2f} ms, GPU kernels {kernel_ms:.2f} ms "
            f"({100 * kernel_ms / ms:.0f}% busy), {launches:.0f} launches per step; top kernels (ms per step):"
        )
        for name, kms, calls in top:
            print(f"  {kms:7.3f} ms  {calls:5.1f}x  {name[:110]}")
    return 0


def host_profile(step: Callable[[], None], device: torch.device, steps: int = 200):
    """(Python wall us per step under cProfile, the 15 functions with the most own time as (name, us per step,
    calls per step)); the GPU is synchronised once per step so queued kernels do not throttle the host."""
    import cProfile
    import pstats

    step()
    profiler = cProfile.Profile()
    start = time.perf_counter()
    profiler.enable()
    for _ in range(steps):
        step()
        if device.type == "cuda":
            torch.cuda.synchronize()
    profiler.disable()
    wall_us = (time.perf_counter() - start) * 1e6 / steps
    stats = pstats.Stats(profiler).stats  # {(file, line, name): (calls, primitive calls, own s, cumulative s, ...)}
    rows = sorted(stats.items(), key=lambda kv: -kv[1][2])[:15]
    top = [
        (f"{Path(f).name}:{line} {name}", own * 1e6 / steps, calls / steps)
        for (f, line, name), (calls, _, own, *_rest) in rows
    ]
    return wall_us, top


def block_vote_maps(width: int, height: int, levels: int, device: torch.device, seed: int = 3):
    """(flat labels [L, H*W], centroids [L, K+1, 2] float32, voting pixels [C]) of square masks, in the training
    batch's dtypes (``vote_maps.label_tensor``: int16 while the ids fit; int32 voting pixels):
    level l tiles the image with squares of side 96 / 2^l px (at most a quarter of the shorter side), a fifth of them left without a mask (label 0),
    each mask's centroid the middle of its square (pixel-index frame; NaN in row 0 and for unmasked squares)."""
    from votesplat_ns.core.vote_maps import label_tensor, voting_pixels

    g = torch.Generator().manual_seed(seed)
    rows, cols = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    label_maps, centroid_tables = [], []
    for level in range(levels):
        side = max(4, min(96, min(width, height) // 4) >> level)
        wide = -(-width // side)
        count = wide * -(-height // side)
        labels = (rows // side) * wide + cols // side + 1
        masked = torch.rand(count + 1, generator=g) >= 0.2
        masked[0] = False
        label_maps.append(torch.where(masked[labels], labels, 0))
        square = torch.arange(count)
        middle = torch.stack([(square % wide) * side, (square // wide) * side], dim=1).float() + (side - 1) / 2
        table = torch.cat([torch.full((1, 2), math.nan), middle])
        table[~masked] = math.nan
        centroid_tables.append(table)
    rows_max = max(len(t) for t in centroid_tables)
    centroids = torch.full((levels, rows_max, 2), math.nan)
    for level, table in enumerate(centroid_tables):
        centroids[level, : len(table)] = table
    labels = label_tensor(torch.stack(label_maps).numpy())
    voting = voting_pixels(labels, centroids)
    return labels.reshape(levels, -1).to(device), centroids.to(device), voting.to(device)


def profile_step(step: Callable[[], None], device: torch.device, steps: int = 5):
    """(GPU kernel ms per step, kernel launches per step, top 10 kernels as (name, ms, calls) per step)."""
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    step()
    with profile(activities=activities) as prof:
        for _ in range(steps):
            step()
        if device.type == "cuda":
            torch.cuda.synchronize()
    kernels = {}
    for event in prof.events():
        if device.type == "cuda" and getattr(event, "device_type", None) != torch.autograd.DeviceType.CUDA:
            continue
        total, calls = kernels.get(event.name, (0.0, 0))
        kernels[event.name] = (total + event.device_time / 1e3, calls + 1)
    total_ms = sum(t for t, _ in kernels.values()) / steps
    launches = sum(c for _, c in kernels.values()) / steps
    top = sorted(kernels.items(), key=lambda kv: -kv[1][0])[:10]
    return total_ms, launches, [(name, t / steps, c / steps) for name, (t, c) in top]


def _mib(value: Optional[float]) -> str:
    return "-" if value is None else f"{value:.0f}"


if __name__ == "__main__":
    sys.exit(main())
