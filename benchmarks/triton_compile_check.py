"""Compiles the Triton vote kernels to sm_90 cubin on CPU, no GPU needed.

Why: ``TRITON_INTERPRET=1`` runs the kernels on CPU tensors (the tests do), but it runs them as
Python: it accepts code that the real compiler rejects (a mask whose type does not match its
pointer's, a layout its passes cannot convert). Compiling every variant for a Hopper target
catches those before a GPU run.

What it compiles, for ``votesplat_ns.core.vote_kernel`` and ``vote_fused``:

* the launches the interpreter tests make (``--record``): it runs pytest under the interpreter
  on the given test files with ``vote_kernel._launch`` (every launch of the vote kernels goes
  through it) wrapped to record each kernel, its argument types (tensors by dtype; ints as
  Triton types them, an int equal to 1 as the constant Triton specialises it to) and its
  compile-time constants; those are compiled as recorded and again with each ``--blocks`` walk
  width (the GPU tests walk 8 and the default 32 entries a block where the interpreter tests
  walk 16). ``--save`` keeps the recording; ``--load`` compiles a saved one (e.g. with another
  Triton on PYTHONPATH, without running the tests again);
* a grid of the production defaults (``--grid``): float32 / float64, 1 and 4 levels, every
  distortion and weighting, table widths 3 and 4.

    python benchmarks/triton_compile_check.py --record tests/test_vote_fused.py tests/test_vote_kernel.py \\
        --save /tmp/launches.json
    PYTHONPATH=/path/to/other/triton:$PWD python benchmarks/triton_compile_check.py --load /tmp/launches.json --grid

Prints one line per variant and ``failures: N``; exits 1 if any failed.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import shlex
import subprocess
import sys
import time

_DTYPES = {
    "float32": "fp32",
    "float64": "fp64",
    "int16": "i16",
    "int32": "i32",
    "int64": "i64",
    "uint8": "u8",
    "bool": "i1",
}
_MODULES = ("votesplat_ns.core.vote_kernel", "votesplat_ns.core.vote_fused")


def _arg_type(value, specialise=True):
    """Triton's type of a launch argument as a signature string, or ("constexpr", value) where it specialises
    (``specialise``: False for a parameter the kernel marks ``do_not_specialize``, whose 1 stays an int)."""
    import torch

    if isinstance(value, torch.Tensor):
        return "*" + _DTYPES[str(value.dtype).removeprefix("torch.")]
    if isinstance(value, bool):
        return "i1"
    if isinstance(value, int):
        if value == 1 and specialise:
            return ["constexpr", 1]
        return "i32" if -(2**31) <= value < 2**31 else "i64"
    if isinstance(value, float):
        return "fp32"
    raise TypeError(f"no signature type for a launch argument of type {type(value).__name__}")


def _unspecialised(kernel):
    """Names of the parameters ``kernel`` marks ``do_not_specialize`` (names or positions in ``triton.jit``); under
    the interpreter the jit options are kept in ``kernel.kwargs``."""
    marked = getattr(kernel, "do_not_specialize", None) or getattr(kernel, "kwargs", {}).get("do_not_specialize")
    return {kernel.arg_names[m] if isinstance(m, int) else m for m in marked or ()}


def record(test_files, pytest_args):
    """Runs pytest under the interpreter on ``test_files`` and returns the distinct launches it made."""
    import pytest

    from votesplat_ns.core import vote_kernel

    seen = {}
    launch = vote_kernel._launch

    def recording(kernel, grid, *args, **kwargs):
        fn = getattr(kernel, "fn", kernel)
        options = {"num_warps": kwargs.get("num_warps", 4)}
        constexprs = {k: v for k, v in kwargs.items() if k not in ("num_warps", "num_stages")}
        types = [_arg_type(a, name not in _unspecialised(kernel)) for name, a in zip(kernel.arg_names, args)]
        entry = {"kernel": fn.__name__, "args": types, "constexprs": constexprs}
        entry["options"] = options
        seen.setdefault(json.dumps(entry, sort_keys=True), entry)
        return launch(kernel, grid, *args, **kwargs)

    vote_kernel._launch = recording
    try:
        code = pytest.main(["-q", "-p", "no:cacheprovider", *pytest_args, *test_files])
    finally:
        vote_kernel._launch = launch
    if code not in (0, 5):
        raise SystemExit(f"the recorded tests failed (pytest exit code {code})")
    return list(seen.values())


def grid_launches():
    """The production defaults' variants (BLOCK 32, PAIR_BLOCK 32; scratch rows as long as a voting set at the
    default threshold can be, vote_kernel.member_slots, and CAP 128 where a kernel has none), as launch records."""
    from votesplat_ns.core import vote_kernel as vk
    from votesplat_ns.core.vote_render import ALPHA_MIN, COLOUR_STOP_T, VoteRenderOptions

    def entry(kernel, args, constexprs):
        return {"kernel": kernel, "args": args, "constexprs": constexprs, "options": {"num_warps": vk.NUM_WARPS}}

    walk = dict(BLOCK=32, CAP=128, PB=32)
    slots = vk.member_slots(VoteRenderOptions().vote_transmittance, ALPHA_MIN, COLOUR_STOP_T, 1)
    fused_walk = dict(walk, CAP=slots)
    out = []
    for fp, levels, dist in itertools.product(("fp32", "fp64"), (1, 4), (0, 1, 2)):
        lp = vk._pow2(levels)
        f, i32, i64, u8 = "*" + fp, "*i32", "*i64", "*u8"
        fwd = dict(LEVELS=levels, LP=lp, DIST=dist, IN_PIXELS=dist == 1, **fused_walk)
        # vote_losses_tiled: the sampling pointers are placeholders (the tile offsets), its map ints 1 and 1.0
        # (the vote means pointer is the votes' own placeholder there)
        tiled = [f, f, f, f, f, f, f, f, f, u8, i32, i32, i32, i32, i32, i32, f, i64, i32, f]
        out.append(entry("_fused_fwd_kernel", tiled + ["i32"] * 9 + ["fp32"], dict(fwd, SAMPLED=False, PROJECT=1)))
        if fp == "fp32":  # vote_losses_sampled takes float32 only
            # the target and valid pointers are placeholders too (the position buffer, the draws); the vote maps
            # as training passes them (int32 voting pixels, int16 labels) and in the wide dtypes it also takes
            for voting, labels in (("*i32", "*i16"), (i64, i32)):
                sampled = [f, f, f, f, f, f, f, f, f, i64, i64, voting, labels, f, i32, i32, f, i64, i32, f]
                sampled_fwd = dict(fwd, SAMPLED=True, PROJECT=2)
                out.append(entry("_fused_fwd_kernel", sampled + ["i32"] * 9 + ["fp32"], sampled_fwd))
        fused_bwd = [f, f, f, f, f, f, f, i32, f, i64, i32, f, f, f, "i32", f, "i32", f, "fp32", "fp32", f]
        for flags, support in (
            # vote_losses_tiled: no support count (its counts and stamps are the denominator's placeholder)
            (dict(HAS_VOTE=True, HAS_DIST=dist != 0, HAS_TOTAL=False, PROJECT=1, COUNT_SUPPORT=False), [f, f]),
            # a training step: the weighted total's gradient, the support counted
            (dict(HAS_VOTE=False, HAS_DIST=False, HAS_TOTAL=True, PROJECT=2, COUNT_SUPPORT=True), [f, i32]),
        ):
            bwd_constexprs = dict(LEVELS=levels, LP=lp, DIST=dist, **flags, **fused_walk)
            out.append(entry("_fused_bwd_kernel", fused_bwd + support + ["i32"] * 4, bwd_constexprs))
        for alpha_t, d1 in itertools.product((False, True), (3, 4)):
            rows = fused_walk if dist else walk  # rows of member_slots with a distortion (none without)
            c = dict(LEVELS=levels, LP=lp, D1=d1, LDP=vk._pow2(levels * d1), ALPHA_T=alpha_t, DIST=dist, **rows)
            # the member ids' row (int32), or the count's as its placeholder without a distortion
            out.append(entry("_vote_fwd_kernel", [f, f, f, i64, i64, i32, f, i32, i64, f, f, f, f, i32, "i32"], c))
            bwd = [f, f, f, i64, i64, i32, f, i32, f, f, f, f, f, f, i32, "i32"]
            out.append(entry("_vote_bwd_kernel", bwd, dict(c, GEOMETRY_GRAD=alpha_t)))
    out.append(
        entry(
            "_fused_reduce_kernel",
            ["*" + fp] * 6 + ["fp32", "fp32", "i32"],
            dict(LEVELS=2, LP=2, RB=1024),
        )
    )
    return out


def compile_all(launches, blocks):
    """Compiles each launch (and its BLOCK variants) for sm_90; returns the number of failures."""
    import importlib

    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    kernels = {}
    for name in _MODULES:
        module = importlib.import_module(name)
        kernels.update({k: v for k, v in vars(module).items() if isinstance(v, triton.runtime.jit.JITFunction)})
    variants = {}
    for launch in launches:
        for block in [None, *blocks]:
            constexprs = dict(launch["constexprs"])
            if block is not None:
                if "BLOCK" not in constexprs:
                    continue
                constexprs["BLOCK"] = block
            variant = dict(launch, constexprs=constexprs)
            variants.setdefault(json.dumps(variant, sort_keys=True), variant)
    failures = 0
    print(f"triton {triton.__version__}: {len(variants)} variants", flush=True)
    for variant in variants.values():
        fn = kernels[variant["kernel"]]
        signature, constexprs = {}, {}
        positional = [p for p in fn.arg_names if p not in variant["constexprs"]]
        if len(positional) != len(variant["args"]):
            raise SystemExit(f"{variant['kernel']}: {len(variant['args'])} arguments recorded, {len(positional)} taken")
        for name, kind in zip(positional, variant["args"]):
            if isinstance(kind, list):
                signature[name], constexprs[name] = "constexpr", kind[1]
            else:
                signature[name] = kind
        for name, value in variant["constexprs"].items():
            signature[name], constexprs[name] = "constexpr", value
        label = f"{variant['kernel']} {variant['args']} {variant['constexprs']}"
        start = time.time()
        try:
            triton.compile(
                ASTSource(fn, signature, constexprs=constexprs),
                target=GPUTarget("cuda", 90, 32),
                options=variant["options"],
            )
        except Exception as error:  # every compiler error is a finding: report it and go on
            failures += 1
            print(f"FAIL {label}\n{str(error)[:1500]}", flush=True)
            continue
        print(f"ok {label} {time.time() - start:.1f}s", flush=True)
    return failures


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--record", nargs="+", metavar="TEST_FILE", help="test files to run under the interpreter")
    parser.add_argument("--pytest-args", default="-x", help="extra pytest arguments, one string (default: -x)")
    parser.add_argument("--save", help="write the recorded launches to this JSON file")
    parser.add_argument("--load", help="compile the launches of a saved recording")
    parser.add_argument("--grid", action="store_true", help="also compile the production defaults' variants")
    parser.add_argument("--blocks", default="8,32", help="walk widths to compile each recorded launch with too")
    args = parser.parse_args(argv)
    if not (args.record or args.load or args.grid):
        parser.error("nothing to compile: give --record, --load or --grid")
    launches = []
    if args.record:
        # the recording runs in a child under the interpreter; the compiler needs it off
        if os.environ.get("TRITON_INTERPRET") != "1":
            out = args.save or os.path.join(os.environ.get("TMPDIR", "/tmp"), f"vote_launches_{os.getpid()}.json")
            child = [
                sys.executable,
                __file__,
                "--record",
                *args.record,
                "--save",
                out,
                f"--pytest-args={args.pytest_args}",
            ]
            subprocess.run(child, check=True, env={**os.environ, "TRITON_INTERPRET": "1"})
            with open(out) as f:
                launches += json.load(f)
        else:
            recorded = record(args.record, shlex.split(args.pytest_args))
            with open(args.save, "w") as f:
                json.dump(recorded, f, indent=1)
            print(f"recorded {len(recorded)} distinct launches to {args.save}")
            return 0
    if args.load:
        with open(args.load) as f:
            launches += json.load(f)
    if args.grid:
        launches += grid_launches()
    failures = compile_all(launches, [int(b) for b in args.blocks.split(",") if b])
    print("failures:", failures)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
