"""Options of ``votesplat query``, ``click``, ``query-eval`` and ``write-labels`` (paper §3.4).

    votesplat query --load-config RUN/config.yml "red mug" [--clip-model ViT-B-16 --clip-checkpoint W.bin]
                    [--level instance] [--instances EXPORT_DIR] [--views 0 3 5] [--output-dir D] [--top-k 5]
    votesplat click --load-config RUN/config.yml --view 3 --x 64 --y 50 [--isolate | --remove] --output-dir D
    votesplat query-eval --load-config RUN/config.yml --labels LABEL_DIR [--output results.json]
    votesplat write-labels --scene SCENE_DIR --output-dir LABEL_DIR [--frames frame_00005.png ...]

The work is done by ``ns/selection.py`` (the loaded run), ``ns/query.py`` (query, click, LERF-OVS)
and ``eval/synthetic/labels.py``; ``cli/main.py`` parses and reports errors.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import tyro
from typing_extensions import Annotated

from votesplat_ns.core.clustering import ClusteringOptions
from votesplat_ns.core.semantics import DEFAULT_NEGATIVES, ClipEncoder, EncoderProtocol
from votesplat_ns.errors import check_writable_folder, writing_into
from votesplat_ns.eval.lerf_ovs import load_scene_labels
from votesplat_ns.eval.synthetic.labels import write_scene_labels
from votesplat_ns.ns.mask_views import DEFAULT_MASK_VIEWS
from votesplat_ns.ns.query import (
    DEFAULT_CLIP_MODEL,
    FeatureOptions,
    evaluate_queries,
    features_cache_path,
    make_encoder,
    run_click,
    run_query,
    write_json,
)
from votesplat_ns.ns.run import check_run
from votesplat_ns.ns.run_instances import InstanceSettings
from votesplat_ns.ns.selection import QueryScene


@dataclass
class _RunArgs:
    load_config: Path
    """Path to the run's config.yml."""
    level: Optional[str] = None
    """Vote level whose instances are selected, by name or index (default: the first level)."""
    instances: Optional[Path] = None
    """Reuse the instances of a votesplat export folder (its instance_ids.npz) instead of clustering again."""
    min_cluster_size: Optional[int] = None
    """Clustering as votesplat export (ignored with --instances): smallest instance, in Gaussians."""
    min_samples: Optional[int] = None
    """HDBSCAN min_samples (default as votesplat export)."""
    seed: int = 0
    """Seed of the clustering subsample."""
    mask_check: bool = True
    """Check the instances against the run's training masks, as votesplat export does (--mask-check)."""
    mask_check_views: int = DEFAULT_MASK_VIEWS
    """Training views the mask check looks through (as votesplat export)."""
    data: Optional[Path] = None
    """Dataset folder, if it moved since training (default: the one in the config); its cameras are the views."""

    def instance_settings(self) -> InstanceSettings:
        """The run's instances as votesplat export computes them with the same flags (one record per run)."""
        clustering = ClusteringOptions(
            min_cluster_size=self.min_cluster_size, min_samples=self.min_samples, seed=self.seed
        )
        return InstanceSettings.make(clustering, self.mask_check, self.mask_check_views)

    def load_scene(self) -> QueryScene:
        return QueryScene.from_config(
            self.load_config, self.level, self.instances, self.instance_settings(), log=print, data=self.data
        )


@dataclass
class _EncoderArgs(_RunArgs):
    clip_model: str = DEFAULT_CLIP_MODEL
    """open_clip architecture of the checkpoint (e.g. ViT-B-16, as LERF)."""
    clip_checkpoint: Optional[Path] = None
    """open_clip weights file (e.g. open_clip_pytorch_model.bin); never downloaded."""
    clip_random_init: bool = False
    """For testing the wiring only: random CLIP weights, so the ranking is meaningless."""
    threshold: Optional[float] = None
    """Select every instance with relevancy >= this (default: only the best one)."""
    negatives: Tuple[str, ...] = DEFAULT_NEGATIVES
    """LERF's canonical phrases the query must beat."""
    feature_views: Optional[int] = 64
    """Training views (evenly spaced) whose crops make the instance features; 0: all."""
    feature_width: int = 512
    """Width in pixels at which feature views are rendered and cropped."""
    min_pixels: int = 64
    """Pixels an instance must cover in a view for that view to count."""
    features_cache: Optional[Path] = None
    """Feature cache folder (default: <run>/votesplat_query)."""

    def encoder(self) -> ClipEncoder:
        return make_encoder(self.clip_model, self.clip_checkpoint, self.clip_random_init)

    def feature_options(self) -> FeatureOptions:
        return FeatureOptions(
            feature_views=self.feature_views, feature_width=self.feature_width, min_pixels=self.min_pixels
        )


@dataclass
class Query(_EncoderArgs):
    """Find the instances a text describes: print the ranking, write masks and renders of the selection."""

    text: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="TEXT")] = ""
    """What to look for, e.g. "red mug"."""
    views: Optional[Tuple[int, ...]] = None
    """Training views to write a mask and render for (default: 4 evenly spaced)."""
    output_dir: Optional[Path] = None
    """Where to write (default: <run>/votesplat_query/<query>)."""
    top_k: int = 5
    """Ranked instances to print."""

    def run(self, encoder: Optional[EncoderProtocol] = None, scene: Optional[QueryScene] = None) -> Dict[str, Any]:
        if not self.text.strip():
            raise ValueError(
                f'the text query is empty ({self.text!r}); pass the words to look for, e.g. votesplat query --load-config C "red mug"'
            )
        if self.output_dir is not None:
            check_writable_folder(self.output_dir, "--output-dir")
        if scene is None:
            check_run(self.load_config)  # a run that cannot load fails before the seconds of building CLIP
        encoder = encoder or self.encoder()
        check_text_length = getattr(encoder, "check_text_length", None)
        if check_text_length is not None:  # before the run is loaded
            check_text_length([self.text, *self.negatives])
        scene = scene or self.load_scene()
        cache = features_cache_path(scene, self.features_cache)
        output_dir = self.output_dir if self.output_dir is not None else scene.run_dir or Path(".")
        with writing_into(output_dir, "--output-dir"):
            return run_query(
                scene,
                self.text,
                encoder,
                self.output_dir,
                self.views,
                self.top_k,
                self.threshold,
                self.negatives,
                self.feature_options(),
                cache,
            )


@dataclass
class Click(_RunArgs):
    """Select the instance under a pixel of a training view; write it alone (or the scene without it) as a PLY."""

    view: int = tyro.MISSING
    """Training view index (0-based, in the run's training image order)."""
    x: float = tyro.MISSING
    """Pixel column, continuous (column c spans [c, c+1)), at the training image's resolution."""
    y: float = tyro.MISSING
    """Pixel row, continuous."""
    output_dir: Path = tyro.MISSING
    """Where the PLY, the render and click.json go (created)."""
    isolate: bool = False
    """Write the clicked instance alone (the default when neither flag is given)."""
    remove: bool = False
    """Write the scene without the clicked instance."""

    def run(self, scene: Optional[QueryScene] = None) -> Dict[str, Any]:
        if self.isolate and self.remove:
            raise ValueError("--isolate and --remove exclude each other; pass one of them")
        check_writable_folder(self.output_dir, "--output-dir")  # before the run is loaded
        scene = scene or self.load_scene()
        with writing_into(self.output_dir, "--output-dir"):
            return run_click(scene, self.view, self.x, self.y, self.output_dir, "remove" if self.remove else "isolate")


@dataclass
class QueryEval(_EncoderArgs):
    """LERF-OVS style 3D selection score: per labelled frame and category, select by text, IoU of the silhouette."""

    labels: Path = tyro.MISSING
    """Folder of LERF-OVS label files (frame_*.json) of this run's images."""
    output: Optional[Path] = None
    """Also write the per-query scores as JSON here."""

    def run(self, encoder: Optional[EncoderProtocol] = None, scene: Optional[QueryScene] = None) -> Dict[str, Any]:
        if self.output is not None:
            check_writable_folder(Path(self.output).parent, "--output", given=self.output)
        frames = load_scene_labels(self.labels, "--labels")
        if scene is None:
            check_run(self.load_config)  # a run that cannot load fails before the seconds of building CLIP
        encoder = encoder or self.encoder()
        scene = scene or self.load_scene()
        cache = features_cache_path(scene, self.features_cache)
        score, selections = evaluate_queries(
            scene,
            frames,
            encoder,
            self.threshold,
            self.negatives,
            self.feature_options(),
            cache,
            scene_name=self.labels.name,
        )
        summary = score.to_dict()
        summary["selections"] = selections
        summary["encoder"] = dict(encoder.config)
        for query in score.queries:
            print(
                f"{query.frame:>16}  {query.category:<24} IoU {query.iou:.3f}  selected {selections.get(query.category)}"
            )
        print(
            f"{score.scene or 'scene'}: {len(score.queries)} queries, mIoU {score.miou:.4f}, mAcc@0.25 {score.accuracy(0.25):.4f}"
        )
        if self.output is not None:
            with writing_into(Path(self.output), "--output"):
                write_json(Path(self.output), summary)
        return summary


@dataclass
class WriteLabels:
    """Write LERF-OVS label files from a scene's ground-truth instance masks and object names."""

    scene: Path
    """Scene folder with transforms.json listing 'instances' (id, name) and per-frame instance_mask_path."""
    output_dir: Path
    """Folder for the label files (<image stem>.json)."""
    frames: Optional[Tuple[str, ...]] = None
    """Image file names to label (default: the scene's evaluation frames)."""

    def run(self) -> List[Path]:
        paths = write_scene_labels(self.scene, self.output_dir, self.frames)
        print(f"Wrote {len(paths)} label files to {self.output_dir}")
        return paths
