"""``votesplat synth``: render a seeded synthetic scene into a nerfstudio dataset with exact labels.

Example (the bundled demo scene)::

    votesplat synth tabletop360 --seed 3 --views 30 --eval-views 4 --width 128 --height 128 \\
        --objects 5 --spp 64 --output-dir votesplat_ns/data/demo --overwrite

A whole set of the ``family`` benchmark (votesplat_ns/eval/synthetic/family.py: tuning or test seeds)::

    votesplat synth family-set --set test --output-dir build/family_test
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from typing import Callable, Iterator, List, Optional

from votesplat_ns.eval.synthetic.scenes import RECIPES

_DEFAULT_VIEWS = {"tabletop360": 48, "nested": 48, "forward": 24, "family": 48}
FAMILY_SET_COMMAND = "family-set"


def build_parser(prog: str = "votesplat synth") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog,
        description="Render a synthetic multi-view scene (mitsuba 3, CPU) with exact instance/part ids and depth.",
        epilog=f"'{prog} {FAMILY_SET_COMMAND} --help': render a whole tuning or test set of the family recipe.",
    )
    parser.add_argument("recipe", choices=sorted(RECIPES), help="scene recipe")
    parser.add_argument("--output-dir", required=True, help="dataset folder to write (transforms.json, images/, ...)")
    parser.add_argument("--seed", type=int, default=0, help="scene seed (objects, cameras, textures, lights)")
    parser.add_argument("--views", type=int, default=None, help="training views (default: 48, forward: 24)")
    parser.add_argument("--eval-views", type=int, default=None, help="held-out views (default: 6, forward: 4)")
    parser.add_argument("--width", type=int, default=256, help="image width in pixels")
    parser.add_argument("--height", type=int, default=192, help="image height in pixels")
    parser.add_argument(
        "--objects", type=int, default=None, help="number of objects (default: the recipe's random count)"
    )
    parser.add_argument("--fov", type=float, default=None, help="horizontal field of view in degrees")
    _add_render_arguments(parser, "png", "points in sparse_pc.ply")
    parser.add_argument("--overwrite", action="store_true", help="replace a dataset already in --output-dir")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    return parser


def _add_render_arguments(parser: argparse.ArgumentParser, default_format: str, points_help: str) -> None:
    """The options of :func:`_render_settings`."""
    parser.add_argument("--spp", type=int, default=64, help="path-tracer samples per pixel for the RGB images")
    parser.add_argument("--max-depth", type=int, default=4, help="path-tracer maximum path length")
    parser.add_argument("--points", type=int, default=4000, help=points_help)
    parser.add_argument(
        "--image-format",
        choices=["png", "jpg"],
        default=default_format,
        help=f"RGB image files (default {default_format}); instance/part labels and depth are always lossless PNG",
    )
    parser.add_argument("--jpeg-quality", type=int, default=95, help="JPEG quality 1-100 with --image-format jpg")


def build_family_set_parser(prog: str = "votesplat synth") -> argparse.ArgumentParser:
    from votesplat_ns.eval.synthetic.family import FAMILY_SETS, SET_OPTIONS

    parser = argparse.ArgumentParser(
        prog=f"{prog} {FAMILY_SET_COMMAND}",
        description=(
            "Render every scene of a family set (votesplat_ns/eval/synthetic/family.py) into <output-dir>/family_<seed>/ "
            f"at {SET_OPTIONS['width']}x{SET_OPTIONS['height']}, {SET_OPTIONS['num_views']} train + "
            f"{SET_OPTIONS['num_eval_views']} held-out views, plus family_set.json. No default may be tuned on the test set."
        ),
    )
    parser.add_argument("--set", required=True, choices=sorted(FAMILY_SETS), help="tuning or test seeds")
    parser.add_argument("--output-dir", required=True, help="folder for the set's scene folders")
    _add_render_arguments(parser, "jpg", "points in each sparse_pc.ply")
    parser.add_argument("--overwrite", action="store_true", help="replace a set already in --output-dir")
    parser.add_argument("--quiet", action="store_true", help="no progress output")
    return parser


def family_set_main(argv: List[str], prog: str = "votesplat synth") -> int:
    """Bad input raises ValueError (``votesplat synth`` prints it as one line)."""
    args = build_family_set_parser(prog).parse_args(argv)
    from votesplat_ns.eval.synthetic.family import write_family_set

    show = _progress_line(args.quiet)

    def progress(scene: int, scenes: int, done: int, total: int) -> None:
        show(f"scene {scene + 1}/{scenes}: rendered {done}/{total} views")

    settings = _render_settings(args)
    with _end_progress_line(args.quiet):
        manifest = write_family_set(args.set, args.output_dir, settings, overwrite=args.overwrite, progress=progress)
    if not args.quiet:
        import json

        info = json.loads(manifest.read_text(encoding="utf-8"))
        print(
            f"\nwrote {manifest}: {len(info['scenes'])} scenes, {info['total_bytes'] / 1e6:.1f} MB, "
            f"{info['total_render_seconds']:.0f} s",
            file=sys.stderr,
        )
    return 0


def _render_settings(args: argparse.Namespace):
    from votesplat_ns.eval.synthetic.render import RenderSettings

    return RenderSettings(args.spp, args.max_depth, args.points, args.image_format, args.jpeg_quality)


def _progress_line(quiet: bool) -> Callable[[str], None]:
    """Rewrites one stderr line with a text and the seconds since this call (nothing when ``quiet``)."""
    start = time.time()

    def show(text: str) -> None:
        if not quiet:
            print(f"\r{text} ({time.time() - start:.0f} s)", end="", file=sys.stderr, flush=True)

    return show


@contextlib.contextmanager
def _end_progress_line(quiet: bool) -> Iterator[None]:
    """An error message starts on a line of its own, not after the progress counter."""
    try:
        yield
    except BaseException:
        if not quiet:
            print(file=sys.stderr)
        raise


def main(argv: Optional[List[str]] = None, prog: str = "votesplat synth") -> int:
    """``votesplat synth``; bad input raises ValueError (or ImportError without mitsuba), printed by the caller as one line."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == [FAMILY_SET_COMMAND]:
        return family_set_main(argv[1:], prog)
    args = build_parser(prog).parse_args(argv)
    from votesplat_ns.eval.synthetic.render import write_dataset
    from votesplat_ns.eval.synthetic.scenes import make_scene

    options = dict(width=args.width, height=args.height)
    options["num_views"] = args.views if args.views is not None else _DEFAULT_VIEWS[args.recipe]
    if args.eval_views is not None:
        options["num_eval_views"] = args.eval_views
    if args.objects is not None:
        options["num_objects"] = args.objects
    if args.fov is not None:
        options["fov_x_degrees"] = args.fov
    show = _progress_line(args.quiet)
    with _end_progress_line(args.quiet):
        scene = make_scene(args.recipe, seed=args.seed, **options)

        def progress(done: int, total: int) -> None:
            show(f"rendered {done}/{total} views")

        out = write_dataset(scene, args.output_dir, _render_settings(args), overwrite=args.overwrite, progress=progress)
    if not args.quiet:
        names = ", ".join(obj.name for obj in scene.objects)
        print(f"\nwrote {out} ({len(scene.cameras)} views, {len(scene.objects)} objects: {names})", file=sys.stderr)
    return 0
