"""Time vote clustering and the instance export on synthetic VoteSplat scenes.

    python benchmarks/bench_clustering.py                       # 100k, 1M, 3M Gaussians + 1M export
    python benchmarks/bench_clustering.py --sizes 100000 --export-size 0 --json out.json
    python benchmarks/bench_clustering.py --sizes --export-size 0 --instances-size 5000000   # a run's instances
    python benchmarks/bench_clustering.py --sizes --export-size 0 --upsample-run <run>/config.yml \
        --upsample-sizes 1000000 5000000 20000000 --json scale.json          # a trained run, upsampled

The scene: ``--instances`` objects of random size; 80% of the Gaussians belong to an object and
vote for its centre (a converged core plus a looser shell and 2% stray votes), 20% are background
(no vote support). Reported per size: wall and CPU seconds of ``cluster_votes_detailed`` on the
foreground votes, the number of instances found and how many Gaussians landed in the instance of
their true object (after matching found to true instances). The export measurement writes the
whole-scene 3DGS PLY (SH degree 3) for ``--export-size`` Gaussians, then runs the full
``export_instances`` (2 levels, one PLY per instance) on the same scene.

``--upsample-run`` takes a trained run (a family scene's, say) and, for each of ``--upsample-sizes``, in a process
of its own (so that its peak memory is its own): loads the run as ``votesplat export`` does, copies its Gaussians
up to that many (:func:`upsampled_scene`: copy k of Gaussian i sits at a random point within its extent, scaled
so the copies fill the same volume, and votes where Gaussian i votes), computes the instances of every level
with the training-mask check (``ns/run_instances.py`` ``compute_instances``, on the run's device) and writes the
export folder (``export_instances``, no picture). Recorded: seconds of each stage, peak host RSS after each
stage and peak GPU memory (torch's allocator) of the instances and of the export, and per level how many
Gaussians fall in the instance of the Gaussian they were copied from, found at the run's own size (after
matching the found instances to those; background counted as a class): the instances must not change as the
same scene gets more Gaussians.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from votesplat_ns.core.clustering import ClusteringOptions, cluster_votes_detailed  # noqa: E402
from votesplat_ns.core.ply_io import gaussian_vertex_table, write_gaussian_table  # noqa: E402
from votesplat_ns.ns.instance_export import export_instances  # noqa: E402


def synthetic_scene(num_gaussians: int, num_instances: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-10, 10, size=(num_instances, 3))
    radii = rng.uniform(0.3, 1.0, size=num_instances)
    weights = rng.uniform(0.2, 1.0, size=num_instances)
    num_fg = int(0.8 * num_gaussians)
    truth = rng.choice(num_instances, size=num_fg, p=weights / weights.sum())
    directions = rng.normal(size=(num_fg, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    means = centres[truth] + directions * radii[truth, None]  # Gaussians on the object surfaces
    # votes: 60% converged (tight), 38% a looser shell, 2% strays anywhere
    kind = rng.random(num_fg)
    spread = np.where(kind < 0.6, 0.01, 0.08)[:, None] * radii[truth, None]
    votes = centres[truth] + rng.normal(size=(num_fg, 3)) * spread
    strays = kind > 0.98
    votes[strays] = rng.uniform(-11, 11, size=(int(strays.sum()), 3))
    background = rng.uniform(-12, 12, size=(num_gaussians - num_fg, 3)) * [1, 1, 0.1] + [0, 0, -11]
    return np.concatenate([means, background]), votes, truth


def matched_fraction(truth: np.ndarray, labels: np.ndarray) -> float:
    """Share of votes whose found instance is the one matched to their true object."""
    from scipy.optimize import linear_sum_assignment

    found = labels >= 0
    k_true, k_found = truth.max() + 1, labels.max() + 1
    table = np.zeros((k_true, k_found))
    np.add.at(table, (truth[found], labels[found]), 1)
    rows, cols = linear_sum_assignment(-table)
    return float(table[rows, cols].sum() / truth.size)


def bench_clustering(size: int, num_instances: int, max_points: int) -> dict:
    means, votes, truth = synthetic_scene(size, num_instances)
    wall, cpu = time.perf_counter(), time.process_time()
    result = cluster_votes_detailed(votes, max_points=max_points)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    return {
        "gaussians": size,
        "foreground_votes": int(votes.shape[0]),
        "wall_s": round(wall, 2),
        "cpu_s": round(cpu, 2),
        "instances_true": num_instances,
        "instances_found": result.num_clusters,
        "noise_votes": result.params["num_noise"],
        "matched_fraction": round(matched_fraction(truth, result.labels), 4),
        "params": {
            k: result.params[k]
            for k in ("min_cluster_size", "sample_min_cluster_size", "min_samples", "num_clustered_points")
        },
    }


def bench_export(size: int, num_instances: int, max_points: int) -> dict:
    import torch

    rng = np.random.default_rng(1)
    means, votes, truth = synthetic_scene(size, num_instances)
    n, num_fg = means.shape[0], votes.shape[0]
    offsets = np.zeros((n, 2, 3), np.float32)
    offsets[:num_fg, 0] = votes - means[:num_fg]
    offsets[:num_fg, 1] = votes - means[:num_fg]  # a second level with the same votes
    support = np.zeros((n, 2), np.float32)
    support[:num_fg] = 1
    params = {
        "means": torch.tensor(means, dtype=torch.float32),
        "scales": torch.tensor(rng.normal(-4, 0.3, size=(n, 3)), dtype=torch.float32),
        "quats": torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32),
        "features_dc": torch.tensor(rng.normal(size=(n, 3)), dtype=torch.float32),
        "features_rest": torch.tensor(rng.normal(size=(n, 15, 3)), dtype=torch.float32),
        "opacities": torch.tensor(rng.normal(1, 1, size=(n, 1)), dtype=torch.float32),
        "vote_offsets": torch.tensor(offsets),
        "vote_support": torch.tensor(support),
    }
    with tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_TMP")) as folder:
        wall = time.perf_counter()
        table = gaussian_vertex_table(
            params["means"],
            params["features_dc"],
            params["features_rest"],
            params["opacities"],
            params["scales"],
            params["quats"],
        )
        write_gaussian_table(Path(folder) / "scene.ply", table)
        ply_wall = time.perf_counter() - wall
        ply_mb = (Path(folder) / "scene.ply").stat().st_size / 2**20
        wall, cpu = time.perf_counter(), time.process_time()
        manifest = export_instances(
            params,
            Path(folder) / "export",
            level_names=("instance", "part"),
            clustering=ClusteringOptions(max_points=max_points),
            progress=False,
        )
        export_wall, export_cpu = time.perf_counter() - wall, time.process_time() - cpu
    return {
        "gaussians": size,
        "scene_ply_write_s": round(ply_wall, 2),
        "scene_ply_mb": round(ply_mb, 1),
        "export_instances_2_levels_wall_s": round(export_wall, 2),
        "export_instances_2_levels_cpu_s": round(export_cpu, 2),
        "instances_found": manifest["levels"][0]["num_instances"],
    }


def synthetic_mask_table(truth: np.ndarray, num_gaussians: int, num_views: int, seed: int = 2) -> np.ndarray:
    """[V, N] int32 mask table as the training-mask check builds it (mask id under each Gaussian, 0 in no mask,
    -1 unseen): each view sees a random 40% of the Gaussians, an object's Gaussians in its own mask (id = object
    + 1) but 5% of them on a mask edge (0), background Gaussians in no mask."""
    rng = np.random.default_rng(seed)
    table = np.full((num_views, num_gaussians), -1, dtype=np.int32)
    labels = np.zeros(num_gaussians, dtype=np.int32)
    labels[: truth.size] = truth + 1
    for view in range(num_views):
        seen = rng.random(num_gaussians) < 0.4
        row = np.where(rng.random(num_gaussians) < 0.05, 0, labels)
        table[view, seen] = row[seen]
    return table


def bench_instances(size: int, num_instances: int, max_points: int, num_views: int) -> dict:
    """The instance computation of a run (ns/run_instances.py compute_instances) without its renders: the vote
    clustering, then the training-mask check and the whole-object rules on a mask table of ``num_views`` views."""
    import resource

    from votesplat_ns.core.clustering import cluster_levels
    from votesplat_ns.core.mask_consensus import regroup_with_masks

    means, votes, truth = synthetic_scene(size, num_instances)
    n, num_fg = means.shape[0], votes.shape[0]
    offsets = np.zeros((n, 1, 3), np.float32)
    offsets[:num_fg, 0] = votes - means[:num_fg]
    support = np.zeros((n, 1), np.float32)
    support[:num_fg] = 1
    table = synthetic_mask_table(truth, n, num_views)
    level_votes = np.full((n, 3), np.nan)
    level_votes[:num_fg] = votes
    wall, cpu = time.perf_counter(), time.process_time()
    instances = cluster_levels(
        means,
        offsets,
        support,
        ("instance",),
        max_points=max_points,
        refine=lambda index, name, ids: regroup_with_masks(ids, means, table, votes=level_votes),
    )
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    level = instances.level("instance")
    return {
        "gaussians": size,
        "views": num_views,
        "mask_table_mb": round(table.nbytes / 2**20, 1),
        "wall_s": round(wall, 2),
        "cpu_s": round(cpu, 2),
        "peak_rss_gb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2),
        "instances_true": num_instances,
        "instances_found": level.num_instances,
        "matched_fraction": round(matched_fraction(truth, level.ids[:num_fg]), 4),
        "objects": level.clustering.get("mask_check", {}).get("objects"),
    }


def upsampled_scene(scene, size: int, seed: int = 0):
    """(``scene``'s Gaussians copied up to ``size``, the index of each one's original): Gaussian j copies Gaussian
    j % N. Copies past the first move by a normal offset of half the original's mean scale and shrink so that the
    c copies of a Gaussian fill its volume (log scale - log(c) / 3); every copy's vote stays the original's."""
    from votesplat_ns.core.scene import TrainedScene

    n = scene.num_gaussians
    parents = np.arange(size, dtype=np.int64) % n
    copies = max(1.0, size / n)
    rng = np.random.default_rng(seed)
    spread = 0.5 * np.exp(scene.log_scales.astype(np.float64)).mean(axis=1).astype(np.float32)
    jitter = rng.standard_normal((size, 3), dtype=np.float32)
    jitter *= spread[parents][:, None]
    jitter[: min(n, size)] = 0.0  # the first copy is the original
    means = scene.means[parents] + jitter
    offsets = scene.vote_offsets[parents]
    offsets -= jitter[:, None, :]  # the vote point (mean + offset) of every copy is its original's
    del jitter
    return (
        TrainedScene(
            means=means,
            log_scales=scene.log_scales[parents] - np.float32(np.log(copies) / 3.0),
            quats=scene.quats[parents],
            opacity_logits=scene.opacity_logits[parents],
            sh_dc=scene.sh_dc[parents],
            sh_rest=None if scene.sh_rest is None else scene.sh_rest[parents],
            vote_offsets=offsets,
            vote_support=scene.vote_support[parents],
            level_names=scene.level_names,
            sh_degree=scene.sh_degree,
            device=scene.device,
        ),
        parents,
    )


def peak_rss_gb() -> float:
    import resource

    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2)


def bench_upsampled_run(
    config: Path, size: int, max_points: int, mask_check: bool, mask_check_views: int, seed: int = 0
) -> dict:
    """One size of ``--upsample-run`` (see the module doc), in this process."""
    import torch

    from votesplat_ns.ns.export import default_rasterizer
    from votesplat_ns.ns.run import load_run
    from votesplat_ns.ns.run_instances import InstanceSettings, compute_instances

    cuda = torch.cuda.is_available()

    def gpu_peak_gb() -> float:
        return round(torch.cuda.max_memory_allocated() / 2**30, 2) if cuda else 0.0

    row: dict = {"gaussians": size, "mask_check": mask_check, "mask_check_views": mask_check_views}

    def progress(stage: str) -> None:
        print(f"[{size} Gaussians] {stage}: {json.dumps(row)}", file=sys.stderr, flush=True)

    wall = time.perf_counter()
    pipeline, scene, _ = load_run(config)
    row.update(run_gaussians=scene.num_gaussians, device=scene.device, load_s=round(time.perf_counter() - wall, 2))
    row["rss_after_load_gb"] = peak_rss_gb()
    progress("loaded")
    settings = InstanceSettings.make(ClusteringOptions(max_points=max_points), mask_check, mask_check_views)
    rasterize = default_rasterizer()
    original, _ = compute_instances(scene, settings, pipeline, rasterize)

    wall = time.perf_counter()
    upsampled, parents = upsampled_scene(scene, size, seed)
    row["upsample_s"] = round(time.perf_counter() - wall, 2)
    row["rss_after_upsample_gb"] = peak_rss_gb()
    progress("copied up")
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    wall = time.perf_counter()
    instances, checked = compute_instances(upsampled, settings, pipeline, rasterize)
    row["instances_s"] = round(time.perf_counter() - wall, 2)
    row["mask_check_ran"] = bool(checked and mask_check)
    row["rss_after_instances_gb"], row["gpu_peak_instances_gb"] = peak_rss_gb(), gpu_peak_gb()
    progress("instances")
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    with tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_TMP")) as folder:
        wall = time.perf_counter()
        manifest = export_instances(upsampled, Path(folder) / "export", instances=instances, progress=False)
        row["export_s"] = round(time.perf_counter() - wall, 2)
        row["export_gb"] = round(sum(p.stat().st_size for p in Path(folder).rglob("*") if p.is_file()) / 2**30, 2)
    row["rss_peak_gb"], row["gpu_peak_export_gb"] = peak_rss_gb(), gpu_peak_gb()
    progress("exported")
    row["levels"] = {}
    for level, before in zip(instances.levels, original.levels):
        row["levels"][level.name] = {
            "instances_at_run_size": before.num_instances,
            "instances": level.num_instances,
            "same_instance_as_original": round(matched_fraction(before.ids[parents] + 1, level.ids + 1), 4),
        }
    row["ply_scene_count"] = manifest["export"]["ply_counts"]["scene"]
    return row


def upsample_sizes_in_processes(args) -> list:
    """Each of ``--upsample-sizes`` in a process of its own (its peak RSS is its own)."""
    import subprocess

    rows = []
    for size in args.upsample_sizes:
        command = [sys.executable, str(Path(__file__).resolve()), "--sizes", "--export-size", "0"]
        command += ["--upsample-run", str(args.upsample_run), "--upsample-one", str(size)]
        command += ["--max-points", str(args.max_points), "--mask-check-views", str(args.mask_check_views)]
        command += [] if args.mask_check else ["--no-mask-check"]
        # the child's stderr (its stage-by-stage progress, warnings, a traceback) goes straight through, so that a run
        # cut short by a time limit still shows how far it came
        result = subprocess.run(command, stdout=subprocess.PIPE, text=True, check=False)
        if result.returncode != 0:
            row = {"gaussians": size, "error": f"exit {result.returncode} (its stderr above)"}
        else:
            row = json.loads(result.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="*", default=[100_000, 1_000_000, 3_000_000])
    parser.add_argument("--export-size", type=int, default=1_000_000, help="0 to skip the export benchmark")
    parser.add_argument("--instances", type=int, default=60)
    parser.add_argument("--max-points", type=int, default=50_000)
    parser.add_argument(
        "--instances-size",
        type=int,
        default=0,
        help="also time the instance computation (clustering, mask check, whole-object rules) at this many Gaussians",
    )
    parser.add_argument("--views", type=int, default=64, help="views of the mask table for --instances-size")
    parser.add_argument("--upsample-run", type=Path, default=None, help="a trained run's config.yml to upsample")
    parser.add_argument(
        "--upsample-sizes", type=int, nargs="*", default=[1_000_000, 5_000_000, 20_000_000], help="for --upsample-run"
    )
    parser.add_argument("--mask-check", action=argparse.BooleanOptionalAction, default=True, help="for --upsample-run")
    parser.add_argument("--mask-check-views", type=int, default=64, help="training views of the mask check")
    parser.add_argument("--upsample-one", type=int, default=0, help=argparse.SUPPRESS)  # one size, in this process
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = parser.parse_args()

    import hdbscan  # noqa: F401  (import cost is not clustering time)

    if args.upsample_one:
        print(
            json.dumps(
                bench_upsampled_run(
                    args.upsample_run, args.upsample_one, args.max_points, args.mask_check, args.mask_check_views
                )
            )
        )
        return
    results = {"cpu_count": os.cpu_count(), "clustering": [], "export": None, "instances": None, "upsampled": None}
    for size in args.sizes:
        row = bench_clustering(size, args.instances, args.max_points)
        results["clustering"].append(row)
        print(json.dumps(row), flush=True)
    if args.export_size:
        results["export"] = bench_export(args.export_size, args.instances, args.max_points)
        print(json.dumps(results["export"]), flush=True)
    if args.instances_size:
        results["instances"] = bench_instances(args.instances_size, args.instances, args.max_points, args.views)
        print(json.dumps(results["instances"]), flush=True)
    if args.upsample_run is not None:
        results["upsampled"] = {"run": str(args.upsample_run), "sizes": upsample_sizes_in_processes(args)}
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
