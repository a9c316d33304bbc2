"""Mean vote error in pixels of trained runs, per level, over every training view, and the same with zero offsets.

    python benchmarks/vote_error.py <run>/config.yml [...]

The error of :meth:`VoteSplatModel.vote_pixel_error` (every pixel with a 2D vote, at the training
image's resolution), averaged over the training views: how far a retrofit's offsets have come
from their start, independent of clustering (e.g. ``--pipeline.model.retrofit-init`` zero vs lifted).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def mean_vote_error(pipeline) -> list:
    import torch

    model, datamanager = pipeline.model, pipeline.datamanager
    cameras = datamanager.train_dataset.cameras
    errors = [model.vote_pixel_error(cameras[i : i + 1], datamanager.vote_batch(i)) for i in range(len(cameras))]
    return torch.nanmean(torch.stack(errors), dim=0).tolist()


def main(argv=None) -> int:
    from nerfstudio.utils.eval_utils import eval_setup

    for config in argv if argv is not None else sys.argv[1:]:
        _, pipeline, _, _ = eval_setup(Path(config), test_mode="val")
        trained = mean_vote_error(pipeline)
        pipeline.model.gauss_params["vote_offsets"].data.zero_()
        zero = mean_vote_error(pipeline)
        levels = pipeline.model.config.vote_levels
        print(
            f"{config}: "
            + ", ".join(f"{name} {t:.2f} px (zero offsets {z:.2f})" for name, t, z in zip(levels, trained, zero)),
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
