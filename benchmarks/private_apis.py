"""What the Gaussians' optimizer path of a training step buys, in whole trainings.

One process trains one scene several times, the same steps and seed each time, and times every step
(the host and the GPU run in lock step in these trainings, so a step's wall time is its cost):

* ``votesplat``: the defaults (``ns/lean_adam.py`` ``LeanFusedAdam`` runs torch's private ``_fused_adam_``
  itself on the Gaussians' groups);
* ``public-fused-adam``: the Gaussians' groups step with ``torch.optim.Adam(fused=True)``;
* ``multi-tensor-adam``: torch's default multi-tensor Adam (``fused=False``), splatfacto's own optimizer;
* ``splatfacto``: nerfstudio's own splatfacto on the same data and steps, with its multi-tensor Adam;
* ``splatfacto-lean-adam``: the same with votesplat's optimizer (``LeanFusedAdam``) on its Gaussian groups, the
  same-optimizer baseline. splatfacto makes ``features_dc`` and ``features_rest`` views of one [N, 16, 3] tensor
  (strides 48 and (48, 3, 1)) while Adam's states are contiguous, and CUDA's fused Adam refuses tensors of
  different strides; so these two get storage of their own after set-up (the same values; the first
  densification would give them that anyway).

Printed per variant: the mean step time before the first vote step and the mean and median after it (vote steps
included), and each one's ratio to ``votesplat``. ``--json`` writes every run and the means::

    python benchmarks/private_apis.py --data build/family_tuning/family_1006 --steps 2000 --vote-start 500
"""

from __future__ import annotations

import argparse
import gc
import json
import statistics
import time
from pathlib import Path
from typing import Callable, Dict, List

VARIANTS = (
    "votesplat",
    "public-fused-adam",
    "multi-tensor-adam",
    "splatfacto",
    "splatfacto-lean-adam",
)


def _configure(variant: str, data: Path, out: Path, steps: int, vote_start: int, device: str):
    import copy

    import torch

    from votesplat_ns.ns.lean_adam import LeanFusedAdam
    from votesplat_ns.ns.method import trainer_config_in_process
    from votesplat_ns.ns.run import SPLAT_PARAM_NAMES  # splatfacto's Gaussian groups

    config = trainer_config_in_process(data, out, steps, vote_start, device, variant, num_downscales=0)
    if variant.startswith("splatfacto"):
        from nerfstudio.configs.method_configs import method_configs

        # nerfstudio's own splatfacto (its datamanager and model), with the run settings of votesplat's
        stock = copy.deepcopy(method_configs["splatfacto"])
        for field in ("machine", "vis", "output_dir", "timestamp", "max_num_iterations", "data"):
            setattr(stock, field, getattr(config, field))
        for field in ("steps_per_eval_image", "steps_per_eval_all_images", "steps_per_save"):
            setattr(stock, field, getattr(config, field))
        stock.pipeline.datamanager.data = data
        stock.pipeline.model.num_downscales = 0
        config = stock
    for name in SPLAT_PARAM_NAMES:
        optimizer = config.optimizers[name]["optimizer"]
        if variant in ("multi-tensor-adam", "splatfacto"):  # splatfacto's own optimizer
            target, fused = torch.optim.Adam, False
        elif variant == "public-fused-adam":
            target, fused = torch.optim.Adam, True
        else:
            target, fused = LeanFusedAdam, True
        optimizer._target = target
        # nerfstudio's AdamOptimizerConfig has no ``fused`` field: its setup passes every field to the optimizer
        optimizer.fused = fused
    config.set_timestamp()
    return config


def _sh_with_storage_of_their_own(trainer) -> None:
    """splatfacto's ``features_dc`` / ``features_rest`` as contiguous parameters (module docstring), in the model
    and in their optimizers (which hold no state before the first step)."""
    import torch

    model = trainer.pipeline.model
    for name in ("features_dc", "features_rest"):
        optimizer = trainer.optimizers.optimizers[name]
        assert not optimizer.state, "set before the first step"
        parameter = torch.nn.Parameter(model.gauss_params[name].detach().clone())
        model.gauss_params[name] = parameter
        optimizer.param_groups[0]["params"] = [parameter]


def _timed_training(config, variant: str) -> List[float]:
    from votesplat_ns.ns.method import setup_trainer
    from votesplat_ns.ns.patches import splatfacto_metrics_at_first_use

    with splatfacto_metrics_at_first_use():  # stock splatfacto's LPIPS would download AlexNet otherwise
        trainer = setup_trainer(config)
    if variant == "splatfacto-lean-adam":
        _sh_with_storage_of_their_own(trainer)
    stamps: List[float] = []
    inner: Callable = trainer.train_iteration

    def timed(step: int):
        result = inner(step)
        stamps.append(time.perf_counter())
        return result

    trainer.train_iteration = timed  # type: ignore[method-assign]
    trainer.train()
    del trainer
    gc.collect()
    return [b - a for a, b in zip(stamps, stamps[1:])]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--vote-start", type=int, default=500)
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    parser.add_argument("--repeats", type=int, default=1, help="runs of each variant, the variants in turn")
    parser.add_argument("--work-dir", type=Path, default=Path("/tmp/votesplat_private_apis"))
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if not 10 <= args.vote_start <= args.steps - 10:
        parser.error("--vote-start must leave at least 10 steps on either side")
    warm_up = min(50, args.vote_start // 5)

    runs: List[Dict[str, object]] = []
    for repeat in range(args.repeats):
        for variant in args.variants:
            config = _configure(variant, args.data, args.work_dir, args.steps, args.vote_start, args.device)
            steps = _timed_training(config, variant)
            # the first steps of each phase (CUDA warm-up, first visits of the views, the vote kernels' JIT
            # compiles in the first run of the process) are left out of its mean
            before = steps[warm_up : args.vote_start - 1]
            after = steps[args.vote_start - 1 + warm_up :]
            run = {
                "variant": variant,
                "repeat": repeat,
                "ms_per_step_before_votes": 1e3 * statistics.fmean(before),
                "ms_per_step_with_votes": 1e3 * statistics.fmean(after),
                "median_ms_with_votes": 1e3 * statistics.median(after),
                "seconds_total": sum(steps),
            }
            runs.append(run)
            print(json.dumps(run), flush=True)
    rows: List[Dict[str, object]] = []
    for variant in args.variants:
        mine = [run for run in runs if run["variant"] == variant]
        mean = lambda key: statistics.fmean(float(run[key]) for run in mine)  # noqa: E731
        row = {
            "variant": variant,
            "runs": len(mine),
            "ms_per_step_before_votes": mean("ms_per_step_before_votes"),
            "ms_per_step_with_votes": mean("ms_per_step_with_votes"),
            "median_ms_with_votes": mean("median_ms_with_votes"),
        }
        rows.append(row)

    by_name = {row["variant"]: row for row in rows}
    print(f"\n{args.data.name}, {args.steps} steps, votes from {args.vote_start}, {args.repeats} run(s) each\n")
    print("| run | ms/step before votes | ms/step with votes (median) | median ratio to votesplat |")
    print("|---|---|---|---|")
    base = by_name.get("votesplat")
    for row in rows:
        ratio = (
            "-" if base is None else f"{float(row['median_ms_with_votes']) / float(base['median_ms_with_votes']):.3f}"
        )
        print(
            f"| {row['variant']} | {float(row['ms_per_step_before_votes']):.2f} | "
            f"{float(row['ms_per_step_with_votes']):.2f} ({float(row['median_ms_with_votes']):.2f}) | {ratio} |"
        )
    if args.json:
        args.json.write_text(json.dumps({"means": rows, "runs": runs}, indent=1))


if __name__ == "__main__":
    main()
