"""Options of ``votesplat eval`` (score a run on a synthetic scene, ``ns/evaluate.py``) and
``votesplat noisy-masks`` (GT masks with SAM-like errors, ``eval/mask_noise.py``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Literal, Optional, Tuple

from votesplat_ns.eval.evaluation import DEFAULT_MAX_PSNR_DROP_DB, DEFAULT_MIN_GAIN_DB
from votesplat_ns.eval.ground_truth import GT_LEVELS
from votesplat_ns.eval.mask_noise import NOISE_MANIFEST_NAME, SAM_LIKE_NOISE, MaskNoise, write_noisy_masks
from votesplat_ns.ns.evaluate import METRICS_NAME, ViewSplit, evaluate_run


@dataclass
class EvaluateVoteSplat:
    """Score a VoteSplat run's instances against a synthetic dataset's exact labels (2D mIoU,
    precision/recall at IoU 0.5 on the held-out views; 3D per-Gaussian purity). Each view's RGB PSNR
    flags views where the reconstruction itself failed; the 2D scores are also given over the valid views."""

    load_config: Path
    """Path to the run's config.yml."""
    output_dir: Optional[Path] = None
    """Folder for metrics.json and the comparison PNGs (default: <run folder>/votesplat_eval)."""
    level: Optional[str] = None
    """Model vote level to score (default: every level with a ground truth of the same name: instance, part)."""
    gt_level: Optional[str] = None
    """Ground truth to compare --level with (instance or part; default: the level's own name)."""
    views: ViewSplit = "eval"
    """Views to score: the held-out views (eval), the training views (train) or both (all)."""
    data: Optional[Path] = None
    """Dataset folder, if it moved since training (default: the one in the config)."""
    min_cluster_size: Optional[int] = None
    """Smallest instance, in Gaussians (default as the export: 0.05 percent of the foreground, at least 10)."""
    min_samples: Optional[int] = None
    """HDBSCAN min_samples (default as the export)."""
    seed: int = 0
    """Seed of the clustering subsample."""
    mask_check: bool = True
    """Check the instances against the training masks, as ns-export votesplat-instances does (--mask-check)."""
    min_weight: float = 0.5
    """A pixel shows an instance if that instance makes up at least this share of the pixel."""
    gaussian_gt: Literal["auto", "geometry", "projection"] = "auto"
    """GT label per Gaussian: scene geometry (exact, needs votesplat synth's generator) or the majority label in the training views."""
    surface_tolerance_px: float = 3.0
    """geometry: a Gaussian farther than this many pixels (at the median camera distance) from every surface is background."""
    max_psnr_drop_db: float = DEFAULT_MAX_PSNR_DROP_DB
    """Reconstruction check: a view whose RGB PSNR is more than this many dB below the median of the scored views
    is a failed reconstruction (6 dB = four times the squared error); inf turns this rule off."""
    min_gain_db: float = DEFAULT_MIN_GAIN_DB
    """Reconstruction check: a view whose RGB PSNR is less than this many dB above that of a flat image of the view's
    mean colour is a failed reconstruction (e.g. a wall of floaters; 2 dB: squared error above 63% of the flat
    image's); -inf turns this rule off."""

    def main(self) -> None:
        # bad input raises ValueError; ``votesplat eval`` prints it as one line
        result = evaluate_run(
            self.load_config,
            self.output_dir,
            level=self.level,
            gt_level=self.gt_level,
            views=self.views,
            data=self.data,
            min_cluster_size=self.min_cluster_size,
            min_samples=self.min_samples,
            seed=self.seed,
            min_weight=self.min_weight,
            gaussian_gt=self.gaussian_gt,
            surface_tolerance_px=self.surface_tolerance_px,
            max_psnr_drop_db=self.max_psnr_drop_db,
            min_gain_db=self.min_gain_db,
            mask_check=self.mask_check,
        )
        print(result.table)
        print(f"wrote {result.output_dir / METRICS_NAME}")


@dataclass
class WriteNoisyMasks:
    """Write a synthetic dataset's GT masks with seeded SAM-like errors (split, merge, boundary jitter,
    drop) as a folder mask source: train with --pipeline.datamanager.mask-source folder
    --pipeline.datamanager.mask-folder <output>."""

    data: Path
    """Dataset folder with GT masks (written by votesplat synth)."""
    output: Path
    """Folder to write (<output>/<level>/<image_stem>.png)."""
    split_rate: float = SAM_LIKE_NOISE.split_rate
    """Probability that a mask is cut in two (over-segmentation)."""
    merge_rate: float = SAM_LIKE_NOISE.merge_rate
    """Probability that a mask absorbs a neighbouring mask (under-segmentation)."""
    jitter_rate: float = SAM_LIKE_NOISE.jitter_rate
    """Probability that a mask's boundary grows or shrinks by 1..max-jitter-px pixels."""
    drop_rate: float = SAM_LIKE_NOISE.drop_rate
    """Probability that a mask is missing."""
    max_jitter_px: int = 2
    merge_max_gap_px: int = 2
    seed: int = 0
    levels: Tuple[str, ...] = GT_LEVELS
    """Levels to write (each needs <level>_mask_path in transforms.json)."""
    overwrite: bool = False
    """Replace a previous noisy-mask folder at --output."""

    def noise(self) -> MaskNoise:
        """The options of the same name as a :class:`MaskNoise` (the CLI's own defaults and help)."""
        return MaskNoise(**{f.name: getattr(self, f.name) for f in fields(MaskNoise)})

    def main(self) -> None:
        out = write_noisy_masks(self.data, self.output, self.noise(), self.levels, self.overwrite)
        manifest = json.loads((out / NOISE_MANIFEST_NAME).read_text(encoding="utf-8"))
        print(
            f"wrote noisy masks for {manifest['num_views']} views, levels {manifest['levels']} to {out}; train with "
            f"--pipeline.datamanager.mask-source folder --pipeline.datamanager.mask-folder {out}"
        )
