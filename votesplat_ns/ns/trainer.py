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

On several processes (``--machine.num-devices N`` or torchrun; a retrofit only) the pipeline is built as for one
process and the ranks meet in the optimizers, which average the offsets' gradients before each step
(:mod:`votesplat_ns.ns.data_parallel` says why nerfstudio's DistributedDataParallel cannot serve).

Ctrl-C: nerfstudio's ``launch`` catches ``KeyboardInterrupt``, prints its traceback and exits 0 with nothing saved.
:class:`VoteSplatTrainer` takes SIGINT itself while it trains: the step under way finishes, a checkpoint of the
last finished step is saved (resume with ``--load-dir``), one line says where, and the command exits 130 (as a
shell does for Ctrl-C). A second Ctrl-C stops at once without saving, also in one line and with 130; so does one
while the run is set up (masks being made), where there is nothing to save yet.
"""

from __future__ import annotations

import signal
import sys
import threading
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple

import torch
from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils import writer
from nerfstudio.utils.rich_utils import CONSOLE

from votesplat_ns.errors import VoteSplatInputError, program_name
from votesplat_ns.ns.data_parallel import (
    COUNTED_GROUPS,
    TRAINED_GROUPS,
    DataParallelOptimizers,
    broadcast_parameters,
    check_data_parallel,
    join_launched_group,
    rank_zero_value,
)
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


INTERRUPTED_EXIT_CODE = 130  # 128 + SIGINT, what a shell reports for a command stopped by Ctrl-C


def interrupted(message: str) -> SystemExit:
    """Print ``<command>: interrupted: <message>`` on stderr; the exit to raise."""
    sys.stderr.write(f"{program_name()}: interrupted: {message}\n")
    sys.stderr.flush()
    return SystemExit(INTERRUPTED_EXIT_CODE)


def _share_run_folder(config: TrainerConfig) -> None:
    """Under torchrun every rank's ns-train named its own run folder by the second it started and saved its
    config.yml there: take rank 0's, and remove a folder of this rank's that holds nothing else."""
    timestamp = rank_zero_value(config.timestamp)
    if timestamp == config.timestamp:
        return
    own = config.get_base_dir()
    config.timestamp = timestamp
    if own.is_dir() and {path.name for path in own.iterdir()} <= {"config.yml"}:
        (own / "config.yml").unlink(missing_ok=True)
        own.rmdir()


def _seed_rank(seed: int) -> None:
    """Seed Python, NumPy and torch as nerfstudio's launch seeds rank r (``--machine.seed`` + r): under torchrun its
    ``train_loop`` sees one process and seeds every rank as rank 0, so all ranks would draw the same vote pixels."""
    import random

    import numpy as np

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


class VoteSplatTrainer(Trainer):
    """nerfstudio's ``Trainer`` whose checkpoint loading reads with ``weights_only=True`` and fails in one line,
    which trains a retrofit on several processes by averaging the offsets' gradients, and which saves a checkpoint
    at Ctrl-C (module docstring)."""

    _interrupted = False
    _last_trained_step: Optional[int] = None

    def __init__(self, config: TrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        launched = join_launched_group(config.machine.device_type) if world_size == 1 else None
        if launched is not None:  # torchrun
            rank, world_size, local_rank = launched
            _seed_rank(config.machine.seed + rank)
            _share_run_folder(config)
        elif world_size > 1 and config.machine.device_type == "cuda":
            torch.cuda.set_device(local_rank)  # nerfstudio's launch leaves every rank's current device at 0
        check_data_parallel(config, world_size)
        self.ranks = world_size
        super().__init__(config, local_rank, world_size)

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        # nerfstudio's pipeline wraps the model in DistributedDataParallel when told of several processes: it is
        # told of one, and the datamanager finds its share of the views in the process group (data_parallel.py)
        self.world_size = 1
        try:
            super().setup(test_mode)
        except KeyboardInterrupt:
            raise interrupted(
                "stopped while the run was set up, before any step was trained; nothing was saved"
            ) from None
        finally:
            self.world_size = self.ranks
        if self.ranks > 1:
            assert isinstance(self.optimizers, DataParallelOptimizers)
            broadcast_parameters(self.optimizers.averaged_parameters())  # every rank starts from rank 0's offsets

    def setup_optimizers(self) -> Optimizers:
        if self.ranks == 1:
            return super().setup_optimizers()
        config, groups = self.config.optimizers.copy(), self.pipeline.get_param_groups()
        return DataParallelOptimizers(config, groups, TRAINED_GROUPS, self.ranks, counted=COUNTED_GROUPS)

    def train_iteration(self, step: int):
        result = super().train_iteration(step)
        self._last_trained_step = step
        return result

    def train(self) -> None:
        if threading.current_thread() is not threading.main_thread():  # signal handlers live in the main thread
            super().train()
            return

        def stop_after_this_step(signum, frame) -> None:
            if self._interrupted:  # a second Ctrl-C
                raise KeyboardInterrupt
            self._interrupted = True
            self.stop_training = True
            CONSOLE.print(
                "Ctrl-C: saving a checkpoint once this step is done (press Ctrl-C again to stop at once, without saving)",
                style="bold yellow",
                markup=False,
            )

        previous = signal.signal(signal.SIGINT, stop_after_this_step)
        try:
            super().train()
        except KeyboardInterrupt:
            self.shutdown()
            raise interrupted(
                "stopped at once by a second Ctrl-C; no checkpoint was saved for the steps since the last one"
            ) from None
        finally:
            signal.signal(signal.SIGINT, previous)
        if self._interrupted:
            self.shutdown()
            step = self._last_trained_step
            if step is None:
                raise interrupted("stopped before the first step was trained; nothing was saved")
            raise interrupted(
                f"stopped after step {step}; saved {self.checkpoint_dir / f'step-{step:09d}.ckpt'}: continue with "
                f"ns-train votesplat ... --load-dir {self.checkpoint_dir}"
            )

    def _after_train(self) -> None:
        if not self._interrupted:
            super()._after_train()
            return
        # interrupted: save the last finished step, and skip the end of training (its callbacks, the viewer's wait)
        self.training_state = "completed"
        if self._last_trained_step is not None:
            self.step = self._last_trained_step
            self.save_checkpoint(self.step)
        writer.write_out_storage()

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
