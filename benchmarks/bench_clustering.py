"""Time vote clustering and the instance export on synthetic VoteSplat scenes.

    python benchmarks/bench_clustering.py                       # 100k, 1M, 3M Gaussians + 1M export
    python benchmarks/bench_clustering.py --sizes 100000 --export-size 0 --json out.json
    python benchmarks/bench_clustering.py --sizes --export-size 0 --instances-size 5000000   # a run's instances

The scene: ``--instances`` objects of random size; 80% of the Gaussians belong to an object and
vote for its centre (a converged core plus a looser shell and 2% stray votes), 20% are background
(no vote support). Reported per size: wall and CPU seconds of ``cluster_votes_detailed`` on the
foreground votes, the number of instances found and how many Gaussians landed in the instance of
their true object (after matching found to true instances). The export measurement writes the
whole-scene 3DGS PLY (SH degree 3) for ``--export-size`` Gaussians, then runs the full
``export_instances`` (2 levels, one PLY per instance) on the same scene.
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
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = parser.parse_args()

    import hdbscan  # noqa: F401  (import cost is not clustering time)

    results = {"cpu_count": os.cpu_count(), "clustering": [], "export": None, "instances": None}
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
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
