"""Cost of the vote pass next to the RGB pass it rides on (GPU only).

Times, on random Gaussians seen by one camera:
  * RGB: gsplat 1.4 ``rasterization`` forward + backward of a full image
    (what splatfacto pays per step);
  * vote: ``render_votes_tiled`` + ``vote_losses`` forward + backward on S
    sampled pixels, reusing the projection and tile lists of a rasterization
    (as the model does: geometry comes from the RGB pass's info).
Prints a markdown table of median milliseconds and peak extra GPU memory.

    python benchmarks/bench_vote_render.py --num-gaussians 500000 --width 1440 --height 1080 --pixels 4096 16384
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
from pathlib import Path
from typing import Callable, List, Tuple

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--num-gaussians", type=int, default=500_000)
    parser.add_argument("--width", type=int, default=1440)
    parser.add_argument("--height", type=int, default=1080)
    parser.add_argument(
        "--pixels", type=int, nargs="+", default=[4096, 16384], help="sampled pixels S for the vote pass"
    )
    parser.add_argument("--chunks", type=int, nargs="+", default=[128], help="render_votes_tiled chunk sizes to time")
    parser.add_argument("--sh-degree", type=int, default=3)
    parser.add_argument("--tile-size", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
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


def measure(step: Callable[[], None], warmup: int, repeats: int) -> Tuple[float, float]:
    """Median milliseconds and peak GPU memory above the starting allocation (MiB)."""
    for _ in range(warmup):
        step()
    torch.cuda.synchronize()
    base = torch.cuda.memory_allocated()
    torch.cuda.reset_peak_memory_stats()
    times: List[float] = []
    for _ in range(repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        step()
        end.record()
        torch.cuda.synchronize()
        times.append(start.elapsed_time(end))
    peak = (torch.cuda.max_memory_allocated() - base) / 2**20
    return statistics.median(times), peak


def main(argv=None) -> int:
    args = parse_args(argv)
    if not torch.cuda.is_available():
        sys.exit(
            "bench_vote_render.py needs a CUDA GPU (gsplat's rasterizer is CUDA-only); none is visible, nothing was timed."
        )
    from gsplat import rasterization

    from votesplat_ns.vote_render import VoteRenderOptions, render_votes_tiled, vote_losses

    device = torch.device("cuda")
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

    rgb_ms, rgb_mib = measure(rgb_step, args.warmup, args.repeats)

    with torch.no_grad():
        _, _, info = rasterize()
    offsets = torch.zeros(args.num_gaussians, 3, device=device, requires_grad=True)
    options = VoteRenderOptions()
    rows = []
    for pixels in args.pixels:
        g = torch.Generator(device=device).manual_seed(args.seed + 1)
        flat = torch.randint(0, args.width * args.height, (pixels,), generator=g, device=device)
        pixel_xy = torch.stack([flat % args.width, flat // args.width], dim=1).float() + 0.5
        target_xy = pixel_xy + 20.0 * torch.randn(pixels, 2, generator=g, device=device)
        valid = torch.ones(pixels, dtype=torch.bool, device=device)
        for chunk in args.chunks:

            def vote_forward():
                votes = params["means"].detach() + offsets
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
                    chunk=chunk,
                )

            def vote_step():
                losses = vote_losses(vote_forward(), target_xy, valid, options)
                (losses["vote"] + 0.1 * losses["distortion"]).backward()

            vote_ms, vote_mib = measure(vote_step, args.warmup, args.repeats)
            with torch.no_grad():
                count = vote_forward().count.float()
            rows.append((pixels, chunk, vote_ms, vote_mib, count.mean().item(), int(count.max().item())))

    run_starts = info["isect_offsets"][0].reshape(-1).long()
    runs = torch.diff(torch.cat([run_starts, run_starts.new_tensor([info["flatten_ids"].numel()])])).float()
    print(
        f"\n{torch.cuda.get_device_name()}, torch {torch.__version__}; {args.num_gaussians} Gaussians at "
        f"{args.width}x{args.height}, SH degree {args.sh_degree}, tile {args.tile_size}; "
        f"{int((info['radii'][0] > 0).sum())} in view, tile runs mean {runs.mean():.0f} / max {runs.max():.0f}; "
        f"median of {args.repeats}\n"
    )
    print("| pass | pixels | chunk | fwd+bwd ms | peak extra MiB | mean \\|M\\| | max \\|M\\| |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    print(f"| RGB rasterization (gsplat) | {args.width * args.height} | - | {rgb_ms:.2f} | {rgb_mib:.0f} | - | - |")
    for pixels, chunk, ms, mib, mean_count, max_count in rows:
        print(
            f"| votes (render_votes_tiled) | {pixels} | {chunk} | {ms:.2f} | {mib:.0f} | {mean_count:.1f} | {max_count} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
