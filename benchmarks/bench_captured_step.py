"""Time the fused vote step's kernels on a captured training step (a trained, densified scene's real inputs).

A capture is written by ``ns-train`` under ``scripts/gpu/run.sh`` with ``VOTESPLAT_CAPTURE_VOTE_STEP=N``
(``benchmarks/train_profile.install_capture``): the arguments of ``vote_losses_sampled`` at the first vote
step at or after N. This script replays that call on CUDA, forward and backward with the support count, as
the training step makes it, and prints

* the walk's shape at those pixels: sampled pixels per tile, tile-list length, run entries walked, |M|
  (the share past ``vote_kernel.CAP``: the slow exact paths when the rows hold only that many members);
* for each walk (``--walks``: ``pixel``, the kernels' one walk, or ``pixel@CAP``, the same with rows of CAP member
  slots as before ``vote_kernel.member_slots``): the GPU time of forward + backward (CUDA events, median
  of ``--reps``), the time of each kernel (torch profiler), and the largest difference of its losses and
  offset gradients from the first walk's.

    python benchmarks/bench_captured_step.py capture.pt [--walks pixel pixel@128] [--reps 50]
"""

from __future__ import annotations

import argparse
import statistics
import sys
from typing import Dict, List

import torch

from votesplat_ns.core import vote_fused, vote_kernel
from votesplat_ns.core.vote_render import VoteRenderOptions

DEFAULT_CAP = vote_kernel.CAP
DEFAULT_SLOT_BYTES = vote_kernel.MEMBER_SLOT_BYTES


def load(path: str, device: torch.device) -> Dict:
    record = torch.load(path, map_location="cpu", weights_only=False)
    for key, value in list(record.items()):
        if isinstance(value, torch.Tensor):
            record[key] = value.to(device)
    record["options"] = VoteRenderOptions(**record["options"])
    return record


def call(record: Dict, offsets: torch.Tensor, support) -> Dict[str, torch.Tensor]:
    """The captured ``vote_losses_sampled`` call with these offsets and support counts."""
    arguments = {name: value for name, value in record.items() if name not in ("step", "offsets", "support")}
    return vote_fused.vote_losses_sampled(**arguments, offsets=offsets, support=support)


def walk_stats(record: Dict) -> List[str]:
    """The sampled pixels' tiles, tile lists, walked entries and |M| (from the forward kernel's walk output)."""
    seen: Dict = {}
    original = vote_kernel._launch

    def launch(kernel, grid, *args, **kwargs):
        original(kernel, grid, *args, **kwargs)
        if "walk" not in seen and kernel is vote_fused._fused_fwd_kernel:
            seen["walk"] = args[kernel.arg_names.index("walk_ptr")].clone()
            seen["pixel_xy"] = args[kernel.arg_names.index("pix_ptr")].clone()

    vote_kernel._launch = launch
    try:
        offsets = record["offsets"].clone().requires_grad_(True)
        call(record, offsets, None)
    finally:
        vote_kernel._launch = original
    count, start, last = seen["walk"].double()
    tiles = record["isect_offsets"]
    tiles_high, tiles_wide = tiles.shape[-2:]
    size = record["tile_size"]
    xy = seen["pixel_xy"]
    tx = (xy[:, 0] / size).floor().long().clamp(0, tiles_wide - 1)
    ty = (xy[:, 1] / size).floor().long().clamp(0, tiles_high - 1)
    tile = ty * tiles_wide + tx
    flat = tiles.reshape(-1)
    ends = torch.cat([flat[1:], flat.new_tensor([record["flatten_ids"].numel()])])
    list_length = (ends - flat)[tile].double()
    walked = (last - start + 1).clamp_min(0)
    per_tile = torch.bincount(tile, minlength=tiles_wide * tiles_high).double()
    used = per_tile[per_tile > 0]

    def describe(name: str, x: torch.Tensor) -> str:
        q = torch.quantile(x, torch.tensor([0.5, 0.9, 0.99], dtype=x.dtype, device=x.device)).tolist()
        return f"{name:<26} mean {x.mean():8.1f}  p50 {q[0]:7.0f}  p90 {q[1]:7.0f}  p99 {q[2]:7.0f}  max {x.max():7.0f}"

    lines = [
        f"step {record['step']}: {record['means'].shape[0]} Gaussians, {record['offsets'].shape[1]} levels, "
        f"{xy.shape[0]} pixels, {record['flatten_ids'].numel()} tile entries, {tiles_wide}x{tiles_high} tiles of {size}",
        describe("sampled pixels per tile", used) + f"  ({used.numel()} tiles with a pixel)",
        describe("tile-list length", list_length),
        describe("entries walked", walked),
        describe("|M|", count),
        f"pixels with |M| > {DEFAULT_CAP} (vote_kernel.CAP): {(count > DEFAULT_CAP).double().mean().item():.1%}",
    ]
    return lines


def time_walk(record: Dict, walk: str, reps: int) -> Dict:
    """``walk`` = pixel or pixel@CAP (``vote_kernel.CAP``, the member slots per pixel, for this run)."""
    name, _, cap = walk.partition("@")
    if name != "pixel":
        raise SystemExit(f"bench_captured_step: --walks takes pixel or pixel@CAP, not {walk!r}")
    vote_kernel.CAP = int(cap) if cap else DEFAULT_CAP
    # with a cap, the fused kernels' rows hold CAP members (as before vote_kernel.member_slots), else every member
    vote_kernel.MEMBER_SLOT_BYTES = 0 if cap else DEFAULT_SLOT_BYTES
    counts = torch.zeros(record["offsets"].shape[:2], device=record["offsets"].device)
    stamps = torch.full(record["offsets"].shape[:2], -1, dtype=torch.int32, device=counts.device)
    offsets = record["offsets"].clone().requires_grad_(True)

    def step(stamp: int):
        offsets.grad = None
        losses = call(record, offsets, (counts, stamps, stamp))
        losses["total"].backward()
        return losses

    for stamp in range(3):  # compile and warm
        step(stamp)
    torch.cuda.synchronize()
    times = []
    for stamp in range(3, 3 + reps):
        begin, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        begin.record()
        step(stamp)
        end.record()
        end.synchronize()
        times.append(begin.elapsed_time(end))
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as profiler:
        for stamp in range(3 + reps, 13 + reps):
            step(stamp)
        torch.cuda.synchronize()
    kernels = {}
    for event in profiler.key_averages():
        if event.device_type == torch.autograd.DeviceType.CUDA and event.count:
            kernels[event.key] = getattr(event, "device_time_total", 0.0) / 10.0 / 1000.0  # ms per step
    counts.zero_()
    stamps.fill_(-1)
    losses = step(10**6)
    return {
        "ms": statistics.median(times),
        "kernels": kernels,
        "vote": losses["vote"].detach(),
        "distortion": losses["distortion"].detach(),
        "grad": offsets.grad.detach().clone(),
        "support": counts.clone(),
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("capture")
    parser.add_argument("--walks", nargs="+", default=["pixel"], help="pixel, pixel@CAP (rows of CAP slots)")
    parser.add_argument("--reps", type=int, default=50)
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        print("bench_captured_step: needs CUDA", file=sys.stderr)
        return 2
    record = load(args.capture, torch.device("cuda"))
    for line in walk_stats(record):
        print(line)
    results = {}
    for walk in args.walks:
        results[walk] = result = time_walk(record, walk, args.reps)
        print(f"\nwalk {walk}: forward + backward {result['ms']:.3f} ms (median of {args.reps})")
        for name, ms in sorted(result["kernels"].items(), key=lambda item: -item[1])[:8]:
            print(f"  {ms:8.3f} ms  {name[:100]}")
        first = results[args.walks[0]]
        if walk != args.walks[0]:
            for key in ("vote", "distortion", "grad", "support"):
                gap = (result[key] - first[key]).abs().max().item()
                scale = first[key].abs().max().item()
                print(f"  max |{key} - {args.walks[0]}'s| = {gap:.3g} (of max {scale:.3g})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
