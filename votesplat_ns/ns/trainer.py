"""votesplat's trainer: nerfstudio's, with a resume (``ns-train votesplat --load-dir / --load-checkpoint``) that
reads checkpoints safely and says one line when it cannot.

nerfstudio 1.1.5's ``Trainer._load_checkpoint`` picks the newest ``step-*`` file in ``--load-dir`` (any other
file there breaks its parse of the names), reads it with ``torch.load`` without ``weights_only`` (safe only
where torch's default is ``weights_only=True``, >= 2.6, and ``TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD`` is unset) and
ends in a traceback for a missing, truncated or foreign file. :class:`VoteSplatTrainer` reads with
``weights_only=True`` always:

* a newest checkpoint that is truncated or damaged (a kill during a save) is skipped, with a warning, for the
  newest one before it that loads;
* a file that is not a weights file (a pickle of anything else: it could run code) stops the run in one line,
  as does a folder without a loadable checkpoint or a ``--load-step`` / ``--load-checkpoint`` that cannot be read.

The rest of the load (pipeline, optimizers, schedulers, gradient scaler) is nerfstudio's, on the loaded state.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import torch
from nerfstudio.engine.trainer import Trainer
from nerfstudio.utils.rich_utils import CONSOLE

from votesplat_ns.errors import VoteSplatInputError
from votesplat_ns.ns.run import checkpoint_failure_reason

DAMAGED = "the file is truncated or damaged"


def read_checkpoint(path: Path) -> Tuple[Optional[Dict[str, Any]], Optional[str]]:
    """(the state, None) of a nerfstudio checkpoint read with ``weights_only=True``, or (None, why not)."""
    if path.stat().st_size == 0:  # a save killed before its first write
        return None, DAMAGED
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for a file that is not a checkpoint
        return None, checkpoint_failure_reason(error, path)
    if not isinstance(state, dict) or not {"step", "pipeline"} <= set(state):
        return None, "it is not a nerfstudio checkpoint (no step and pipeline)"
    return state, None


def step_checkpoints(folder: Path) -> List[Path]:
    """The ``step-<number>.ckpt`` files of ``folder``, newest (highest step) first."""
    found = [path for path in folder.glob("step-*.ckpt") if path.stem[len("step-") :].isdigit()]
    return sorted(found, key=lambda path: int(path.stem[len("step-") :]), reverse=True)


def resume_state(load_dir: Optional[Path], load_step: Optional[int], load_checkpoint: Optional[Path]):
    """(path, state) of the checkpoint a resume starts from, or None (no resume); one-line errors otherwise."""
    if load_dir is not None:
        load_dir = Path(load_dir)
        if load_step is not None:
            candidates = [load_dir / f"step-{load_step:09d}.ckpt"]
            flag = f"--load-dir {load_dir} --load-step {load_step}"
        else:
            candidates = step_checkpoints(load_dir) if load_dir.is_dir() else []
            flag = f"--load-dir {load_dir}"
        if not candidates or not candidates[0].is_file():
            raise VoteSplatInputError(
                f"{flag}: no checkpoint there (step-*.ckpt); give a run's nerfstudio_models/ folder"
                + (" and a step it saved" if load_step is not None else "")
            )
    elif load_checkpoint is not None:
        candidates, flag = [Path(load_checkpoint)], f"--load-checkpoint {load_checkpoint}"
        if not candidates[0].is_file():
            raise VoteSplatInputError(f"{flag}: file not found; give a step-*.ckpt written by ns-train")
    else:
        return None
    skipped = []
    for path in candidates:
        state, problem = read_checkpoint(path)
        if state is not None:
            for damaged in skipped:
                CONSOLE.print(
                    f"Warning: skipping checkpoint {damaged} ({DAMAGED}: a kill during a save can leave one); "
                    f"resuming from {path}",
                    style="bold yellow",
                    soft_wrap=True,
                    markup=False,
                )
            return path, state
        if problem != DAMAGED or len(candidates) == 1 or path == candidates[-1]:
            raise VoteSplatInputError(
                f"{flag}: checkpoint {path} cannot be loaded: {problem}"
                + (f" (newer ones skipped as damaged: {', '.join(p.name for p in skipped)})" if skipped else "")
                + "; resume from a folder of checkpoints ns-train wrote, or train from scratch without --load-dir"
            )
        skipped.append(path)
    return None  # unreachable: the loop returns or raises on its last candidate


class VoteSplatTrainer(Trainer):
    """nerfstudio's ``Trainer`` whose checkpoint loading reads with ``weights_only=True`` and fails in one line."""

    def _load_checkpoint(self) -> None:
        found = resume_state(self.config.load_dir, self.config.load_step, self.config.load_checkpoint)
        if found is None:
            CONSOLE.print("No Nerfstudio checkpoint to load, so training from scratch.")
            return
        path, loaded_state = found
        # nerfstudio 1.1.5 Trainer._load_checkpoint's steps, on the state read above
        self._start_step = loaded_state["step"] + 1
        self.pipeline.load_pipeline(loaded_state["pipeline"], loaded_state["step"])
        self.optimizers.load_optimizers(loaded_state["optimizers"])
        if "schedulers" in loaded_state and self.config.load_scheduler:
            self.optimizers.load_schedulers(loaded_state["schedulers"])
        self.grad_scaler.load_state_dict(loaded_state["scalers"])
        CONSOLE.print(f"Done loading Nerfstudio checkpoint from {path}")
