"""Bring trained runs back from the device machine in a few small files, and open them here.

A device call returns at most 8 files of 16 MiB, so a sweep's checkpoints (hundreds of MiB with
Adam's state) cannot come back as they are. ``pack`` keeps what clustering, export and scoring
read -- the config and the model's parameters, without optimiser state and without the
view-dependent colour (``features_rest``, zeros after ``unpack``: renders keep their base colour, so
PSNR figures of unpacked runs are not the trained ones) -- and splits the runs over at most
``--max-files`` archives. ``unpack`` rewrites every path that pointed into the device's folders
(the repository root, the sweep's work folder) to this machine's and writes a normal run folder
that ``votesplat eval`` / ``ns-export`` load.

    python scripts/gpu/pack_runs.py pack /tmp/votesplat_runs/sweep $OUT --root "$PWD"
    python scripts/gpu/pack_runs.py unpack /work/.device/.../runs_*.pt --dest build/runs_tuning
"""

from __future__ import annotations

import argparse
import io
import sys
from pathlib import Path, PurePath
from typing import Dict, List, Sequence

import torch
import yaml

# float16 is plenty for these (offsets: ~1e-3 relative, far below the votes' spread); means stay
# float32 because a Gaussian can be smaller than float16's step at the scene's extent
HALF_KEYS = ("scales", "quats", "opacities", "features_dc", "vote_offsets", "vote_support")
DROPPED_KEY = "features_rest"


def slim_run(config_path: Path, drop: Sequence[str] = ()) -> Dict[str, object]:
    checkpoints = sorted((config_path.parent / "nerfstudio_models").glob("step-*.ckpt"))
    if not checkpoints:
        raise FileNotFoundError(f"{config_path.parent} has no checkpoint")
    loaded = torch.load(checkpoints[-1], map_location="cpu", weights_only=False)
    state = {}
    rest_shape = None
    dropped = {}
    for key, value in loaded["pipeline"].items():
        if key.endswith(DROPPED_KEY):
            rest_shape = tuple(value.shape)
            continue
        if any(
            key.endswith(k) for k in drop
        ):  # zeros after unpack (e.g. features_dc: instance scores never read colour)
            dropped[key] = tuple(value.shape)
            continue
        if any(key.endswith(k) for k in HALF_KEYS):
            value = value.half()
        state[key] = value.clone()
    return {
        "config": config_path.read_text(),
        "checkpoint_name": checkpoints[-1].name,
        "step": loaded["step"],
        "state": state,
        "rest_shape": rest_shape,
        "dropped": dropped,
        "run_dir": str(config_path.parent),
        "dataparser_transforms": _read_optional(config_path.parent / "dataparser_transforms.json"),
    }


def _read_optional(path: Path):
    return path.read_text() if path.is_file() else None


def pack(
    work_dir: Path,
    out_dir: Path,
    root: str,
    max_files: int,
    max_bytes: int,
    select: List[str],
    drop: Sequence[str] = (),
) -> List[Path]:
    runs = []
    for config in sorted(work_dir.rglob("config.yml")):
        if select and not any(word in str(config.relative_to(work_dir)) for word in select):
            continue
        try:
            runs.append(slim_run(config, drop))
        except FileNotFoundError as err:  # a run cut short by the call's time limit
            print(f"skipped: {err}", file=sys.stderr)
    groups: List[List[dict]] = [[] for _ in range(max(1, min(max_files, len(runs))))]
    sizes = [0] * len(groups)
    for run in sorted(runs, key=lambda r: -sum(v.numel() * v.element_size() for v in r["state"].values())):
        i = sizes.index(min(sizes))
        groups[i].append(run)
        sizes[i] += sum(v.numel() * v.element_size() for v in run["state"].values())
    written = []
    for i, group in enumerate(groups):
        buffer = io.BytesIO()
        torch.save({"root": root, "work_dir": str(work_dir), "runs": group}, buffer)
        path = out_dir / f"runs_{i}.pt"
        path.write_bytes(buffer.getvalue())
        if path.stat().st_size > max_bytes:
            print(f"warning: {path} is {path.stat().st_size / 2**20:.1f} MiB, over the return limit", file=sys.stderr)
        written.append(path)
        print(f"{path}: {len(group)} runs, {path.stat().st_size / 2**20:.1f} MiB")
    return written


def _rewrite_paths(obj, mapping: Dict[str, str], seen=None):
    """Replace path prefixes in every Path field of a loaded nerfstudio config, in place."""
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return obj
    seen.add(id(obj))
    if isinstance(obj, PurePath):
        text = str(obj)
        for old, new in mapping.items():
            if text == old or text.startswith(old + "/"):
                return Path(new + text[len(old) :])
        return obj
    if isinstance(obj, list):
        for i, value in enumerate(obj):
            obj[i] = _rewrite_paths(value, mapping, seen)
        return obj
    if hasattr(obj, "__dict__") and not isinstance(obj, type):
        for key, value in list(vars(obj).items()):
            try:
                setattr(obj, key, _rewrite_paths(value, mapping, seen))
            except (AttributeError, TypeError):
                pass
    return obj


def unpack(archives: List[Path], dest: Path, root: Path) -> List[Path]:
    from votesplat_ns.cli.evaluate_cli import write_noisy_masks
    from votesplat_ns.eval.mask_noise import MaskNoise

    dest = dest.resolve()
    configs = []
    for archive in archives:
        bundle = torch.load(archive, map_location="cpu", weights_only=False)
        mapping = {bundle["work_dir"]: str(dest), bundle["root"]: str(root.resolve())}
        for run in bundle["runs"]:
            config = yaml.load(run["config"], Loader=yaml.Loader)
            config = _rewrite_paths(config, mapping)
            folder = getattr(config.pipeline.datamanager, "mask_folder", None)
            if folder is not None and not Path(folder).is_dir():
                # noisy masks are a pure function of the scene and MaskNoise's seed: rebuild them
                write_noisy_masks(Path(config.data), Path(folder).parent, MaskNoise(), overwrite=True)
            base = config.get_base_dir()
            (base / "nerfstudio_models").mkdir(parents=True, exist_ok=True)
            (base / "config.yml").write_text(yaml.dump(config), "utf8")
            transforms = base / "dataparser_transforms.json"
            if run.get("dataparser_transforms"):
                transforms.write_text(run["dataparser_transforms"])
            else:  # older packs: the dataparser's transform is a pure function of the data and config
                parser_config = config.pipeline.datamanager.dataparser
                parser_config.data = Path(config.data)
                parser = parser_config.setup()
                parser.get_dataparser_outputs(split="train").save_dataparser_transform(transforms)
            state = {k: (v.float() if v.is_floating_point() else v) for k, v in run["state"].items()}
            for key, shape in run.get("dropped", {}).items():
                state[key] = torch.zeros(shape)
            if run["rest_shape"] is not None:
                prefix = next(k for k in state if k.endswith("features_dc"))[: -len("features_dc")]
                state[prefix + DROPPED_KEY] = torch.zeros(run["rest_shape"])
            torch.save({"step": run["step"], "pipeline": state}, base / "nerfstudio_models" / run["checkpoint_name"])
            configs.append(base / "config.yml")
            print(base / "config.yml")
    return configs


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("pack")
    p.add_argument("work_dir", type=Path)
    p.add_argument("out_dir", type=Path)
    p.add_argument("--root", required=True, help="the repository root on this machine (paths under it are rewritten)")
    p.add_argument("--max-files", type=int, default=4)
    p.add_argument("--max-bytes", type=int, default=16 * 2**20)
    p.add_argument("--select", nargs="*", default=[], help="only runs whose path holds one of these words")
    p.add_argument("--drop", nargs="*", default=[], help="parameters left out (zeros after unpack), e.g. features_dc")
    u = sub.add_parser("unpack")
    u.add_argument("archives", nargs="+", type=Path)
    u.add_argument("--dest", type=Path, required=True)
    u.add_argument("--root", type=Path, default=Path.cwd())
    args = parser.parse_args(argv)
    if args.command == "pack":
        pack(args.work_dir, args.out_dir, args.root, args.max_files, args.max_bytes, args.select, args.drop)
    else:
        unpack(args.archives, args.dest, args.root)
    return 0


if __name__ == "__main__":
    sys.exit(main())
