"""The family benchmark: which seeds of the ``family`` recipe tune defaults and which test them.

**No default may be tuned on the test set.** Model config defaults, presets, border, clustering and
merging rules are chosen on :data:`TUNING_SEEDS` only; :data:`TEST_SEEDS` are rendered and scored
to report how those defaults carry over to scenes they were not chosen on.

Each set is the first block of :data:`SET_SIZE` consecutive seeds from its start (1000 tuning,
2000 test) that :func:`covers` (every property kind of :data:`FAMILY_PROPERTY_KINDS`, at least three
360 and two forward-facing captures, a cut-by-frame scene of each capture); ``tuning-extra`` is the
next two such blocks after the tuning block, for decisions that one set of six cannot make. The seeds follow from
the recipe's properties alone, before any scene was rendered or scored; a test checks that the rule
still gives these seeds.

A set is written as ``<output>/family_<seed>/`` datasets (``votesplat synth family-set``) at
:data:`SET_OPTIONS` with JPEG images (masks and depth stay lossless PNG), plus ``family_set.json``.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from pathlib import Path
from typing import Callable, Dict, Iterable, List, Optional, Tuple

from votesplat_ns.eval.synthetic.scenes import FAMILY_PROPERTY_KINDS, FamilyProperties, family_properties

SET_SIZE = 6
TUNING_START, TEST_START = 1000, 2000
TUNING_SEEDS: Tuple[int, ...] = (1006, 1007, 1008, 1009, 1010, 1011)
TEST_SEEDS: Tuple[int, ...] = (2054, 2055, 2056, 2057, 2058, 2059)
# More scenes to tune on, because one set of six moved by more between two trainings than between the
# variants it was to rank: the next two covering blocks after the tuning block (same rule, same range).
TUNING_EXTRA_SEEDS: Tuple[int, ...] = (1054, 1055, 1056, 1057, 1058, 1059, 1060, 1061, 1062, 1063, 1064, 1065)
FAMILY_SETS: Dict[str, Tuple[int, ...]] = {
    "tuning": TUNING_SEEDS,
    "tuning-extra": TUNING_EXTRA_SEEDS,
    "test": TEST_SEEDS,
}
# the scene options every set is rendered with (make_scene("family", seed, **SET_OPTIONS))
SET_OPTIONS = dict(num_views=48, num_eval_views=6, width=256, height=192)
SET_MANIFEST = "family_set.json"


def covers(seeds: Iterable[int]) -> bool:
    """Whether the scenes of ``seeds`` cover every property kind, >= 3 360 and >= 2 forward captures,
    and a cut-by-frame scene of each capture."""
    props = [family_properties(seed) for seed in seeds]
    kinds = {kind for p in props for kind in p.kinds}
    captures = Counter(p.capture for p in props)
    cut_captures = {p.capture for p in props if p.cut_object is not None}
    return (
        kinds >= set(FAMILY_PROPERTY_KINDS)
        and captures["360"] >= 3
        and captures["forward"] >= 2
        and cut_captures == {"360", "forward"}
    )


def covering_block(start: int, size: int = SET_SIZE) -> Tuple[int, ...]:
    """The first block of ``size`` consecutive seeds from ``start`` (in steps of ``size``) that :func:`covers`."""
    first = start
    while not covers(range(first, first + size)):
        first += size
    return tuple(range(first, first + size))


def family_set(name: str) -> List[Tuple[int, FamilyProperties]]:
    """(seed, properties) of every scene of the set ``name`` ("tuning" or "test")."""
    if name not in FAMILY_SETS:
        raise ValueError(f"unknown family set {name!r}; choose one of {', '.join(FAMILY_SETS)}")
    return [(seed, family_properties(seed)) for seed in FAMILY_SETS[name]]


def scene_folder(seed: int) -> str:
    """Folder name of a set's scene (``family_<seed>``)."""
    return f"family_{seed}"


def write_family_set(
    name: str,
    output_dir,
    settings=None,
    overwrite: bool = False,
    progress: Optional[Callable[[int, int, int, int], None]] = None,
) -> Path:
    """Render every scene of set ``name`` into ``output_dir/family_<seed>/`` and write ``family_set.json``
    (seeds, properties, render settings, seconds and bytes per scene); returns the manifest's path.

    ``settings``: a :class:`~votesplat_ns.eval.synthetic.render.RenderSettings` (default: JPEG images at
    quality 95, 64 samples per pixel). ``progress(scene, scenes, view, views)`` is called per view.
    """
    from votesplat_ns.eval.synthetic.dataset_files import write_json
    from votesplat_ns.eval.synthetic.render import RenderSettings, write_dataset
    from votesplat_ns.eval.synthetic.scenes import make_scene

    members = family_set(name)
    settings = settings if settings is not None else RenderSettings(image_format="jpg")
    output_dir = Path(output_dir)
    manifest = output_dir / SET_MANIFEST
    if manifest.exists() and not overwrite:
        raise ValueError(f"{output_dir} already holds a family set ({manifest.name}); pass --overwrite to replace it")
    scenes = []
    for number, (seed, props) in enumerate(members):
        start = time.time()
        scene = make_scene("family", seed=seed, **SET_OPTIONS)
        folder = output_dir / scene_folder(seed)

        def view_done(done: int, total: int, number=number) -> None:
            if progress is not None:
                progress(number, len(members), done, total)

        write_dataset(scene, folder, settings, overwrite=overwrite, progress=view_done)
        size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
        scenes.append(
            {
                "seed": seed,
                "folder": folder.name,
                "properties": props.kinds,
                "objects": [obj.name for obj in scene.objects],
                "cut_view_share": scene.parameters.get("cut_view_share"),
                "render_seconds": round(time.time() - start, 1),
                "bytes": size,
            }
        )
    write_json(
        manifest,
        {
            "set": name,
            "seeds": [seed for seed, _ in members],
            "scene_options": SET_OPTIONS,
            "render": {
                "spp": settings.spp,
                "max_depth": settings.max_depth,
                "image_format": settings.image_format,
                "jpeg_quality": settings.jpeg_quality,
                "points": settings.num_points,
            },
            "note": "no default may be tuned on the test set (votesplat_ns/eval/synthetic/family.py)",
            "scenes": scenes,
            "total_bytes": sum(s["bytes"] for s in scenes),
            "total_render_seconds": round(sum(s["render_seconds"] for s in scenes), 1),
        },
    )
    return manifest


def read_family_set(folder) -> Tuple[str, List[Path]]:
    """(set name, scene folders) of a folder written by :func:`write_family_set`, checked against this set's seeds."""
    folder = Path(folder)
    manifest = folder / SET_MANIFEST
    if not manifest.is_file():
        raise ValueError(
            f"{manifest} not found; write the set with: votesplat synth family-set --set <tuning|test> --output-dir {folder}"
        )
    data = json.loads(manifest.read_text(encoding="utf-8"))
    name = data.get("set")
    if name not in FAMILY_SETS or tuple(data.get("seeds", ())) != FAMILY_SETS[name]:
        raise ValueError(
            f"{manifest} lists set {name!r} with seeds {data.get('seeds')}, not this code's sets; render it again"
        )
    scenes = [folder / scene_folder(seed) for seed in FAMILY_SETS[name]]
    missing = [str(s) for s in scenes if not (s / "transforms.json").is_file()]
    if missing:
        raise ValueError(f"{missing[0]} has no transforms.json (an unfinished set); render it again with --overwrite")
    return name, scenes
