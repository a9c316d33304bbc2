"""Counts the aten ops, host syncs and Triton launches of a vote step on CPU, and builds a model's vote step.

The vote pass is launch-bound on a GPU: its cost is the number of kernels it launches and the host
synchronisations that stall the launch queue. Neither needs a GPU to count: every kernel is one aten op at
the dispatcher, and every host sync is an op that reads a device value on the host or sizes a tensor by device
data. :class:`OpCounter` is a ``TorchDispatchMode`` (it sees autograd's backward ops too) joined with a
``TorchFunctionMode`` (it sees ``Tensor.tolist``, which reads a CPU tensor without an aten op); ops are
attributed to a phase by the functions of ``core/vote_render.py`` on the Python stack when they run.
``model_step`` builds ``VoteSplatModel.vote_loss_terms`` on a CPU model with random Gaussians.
"""

from __future__ import annotations

import sys
from collections import Counter, defaultdict
from typing import Callable, Dict, List, Optional

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

# aten ops that read a device value on the host (on CUDA: wait for the queue) or whose output shape
# depends on device data (the same wait, to size the result).
SYNC_OPS = {
    "_local_scalar_dense",  # item(), int(), float(), bool() of a tensor
    "is_nonzero",
    "item",
    "equal",  # torch.equal returns a Python bool
    "allclose",
    "nonzero",
    "argwhere",
    "masked_select",
    "unique",
    "_unique",
    "_unique2",
    "unique_dim",
    "unique_consecutive",
}
# Tensor methods that read device values without an aten op on CPU.
SYNC_METHODS = {"tolist", "numpy", "cpu", "__array__"}
# Phase of an op by the innermost of these core/vote_render.py functions on the stack.
# ("checks" also holds the lookup of each pixel's tile run, _pixel_runs, which the walk needs.)
CHECK_FUNCTIONS = {
    "_validate_inputs",
    "_validate_tiles",
    "_finiteness_checks",
    "_all_finite",
    "_read_host",
    "_raise_unless",
    "_pixel_runs",
    "_check_render_inputs",
    "_check_loss_inputs",
}
WALK_FUNCTIONS = {"_tiled_members", "_run_entries"}
FINISH_FUNCTIONS = {"_finish"}
RENDER_FILE = "vote_render.py"
# Ops that only make a new view of existing memory: no kernel launch on a GPU.
VIEW_OPS = {
    "view",
    "_unsafe_view",
    "reshape",
    "select",
    "slice",
    "unsqueeze",
    "squeeze",
    "detach",
    "alias",
    "expand",
    "t",
    "transpose",
    "permute",
    "as_strided",
    "split",
    "unbind",
    "narrow",
    "diagonal",
    "lift_fresh",
}
# Ops that only allocate (the caching allocator, no kernel launch on a GPU).
ALLOC_OPS = {"empty", "empty_like", "empty_strided", "new_empty", "new_empty_strided"}


def _is_sync(func, args) -> bool:
    name = func.__name__.split(".")[0]
    if name in SYNC_OPS:
        return True
    if name == "repeat_interleave":
        return len(args) < 1 or "output_size" not in str(args)  # conservative: only the Tensor overload syncs
    if name in ("index", "index_put", "index_put_", "_index_put_impl_"):
        indices = args[1] if len(args) > 1 else ()
        return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in indices if i is not None)
    return False


class _SyncMethods(TorchFunctionMode):
    """Tensor methods that read values on the host without an aten op on CPU (``tolist``)."""

    def __init__(self, owner: "OpCounter"):
        super().__init__()
        self.owner = owner

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", "")
        if name in SYNC_METHODS:
            self.owner._record_sync(name)
        return func(*args, **(kwargs or {}))


class OpCounter(TorchDispatchMode):
    """Counts aten ops and host syncs per phase of the vote step (see the module docstring).

    ``with OpCounter() as counter:``; ``counter.ops[phase]``, ``counter.syncs[phase]`` (a list of
    op names); ``with counter.phase("backward"):`` forces a phase.
    """

    def __init__(self) -> None:
        super().__init__()
        self.ops: Dict[str, int] = Counter()
        self.kernels: Dict[str, int] = Counter()
        self.op_names: Dict[str, Counter] = defaultdict(Counter)
        self.syncs: Dict[str, List[str]] = defaultdict(list)
        self.allocs = 0
        self.triton_launches = 0
        self.triton_names: Dict[str, int] = Counter()
        self._forced: Optional[str] = None
        self._walked = False
        self._methods = _SyncMethods(self)
        self._launch = None
        self._inside_launch = False

    def __enter__(self):
        super().__enter__()
        self._methods.__enter__()
        # Triton kernels are no aten ops: count them where the vote kernels launch (vote_kernel._launch)
        from votesplat_ns.core import vote_kernel

        self._launch = vote_kernel._launch

        def counted(kernel, grid, *args, **kwargs):
            self.triton_launches += 1
            self.triton_names[getattr(kernel, "__name__", str(kernel))] += 1
            assert self._launch is not None
            # Triton's CPU interpreter copies the arguments with torch ops: not the kernel's launches
            self._inside_launch = True
            try:
                return self._launch(kernel, grid, *args, **kwargs)
            finally:
                self._inside_launch = False

        vote_kernel._launch = counted
        return self

    def __exit__(self, *exc):
        from votesplat_ns.core import vote_kernel

        vote_kernel._launch = self._launch
        self._methods.__exit__(*exc)
        return super().__exit__(*exc)

    class _Phase:
        def __init__(self, counter: "OpCounter", name: str):
            self.counter, self.name = counter, name

        def __enter__(self):
            self.previous, self.counter._forced = self.counter._forced, self.name

        def __exit__(self, *exc):
            self.counter._forced = self.previous

    def phase(self, name: str) -> "OpCounter._Phase":
        return OpCounter._Phase(self, name)

    @property
    def total_ops(self) -> int:
        return sum(self.ops.values())

    @property
    def total_kernels(self) -> int:
        return sum(self.kernels.values())

    @property
    def total_syncs(self) -> int:
        return sum(len(v) for v in self.syncs.values())

    def _current_phase(self) -> str:
        if self._forced is not None:
            return self._forced
        frame = sys._getframe(2)
        names = []
        in_model = False
        while frame is not None:
            filename = frame.f_code.co_filename
            if filename.endswith(RENDER_FILE):
                names.append(frame.f_code.co_name)
            elif filename.endswith("model.py") and "votesplat_ns" in filename:
                in_model = True
            frame = frame.f_back
        if not names:
            return "model: sampling" if in_model else "other"
        if "vote_losses" in names:
            return "loss checks" if CHECK_FUNCTIONS.intersection(names) else "losses"
        if WALK_FUNCTIONS.intersection(names):
            self._walked = True
            return "walk"
        if CHECK_FUNCTIONS.intersection(names):
            return "checks"
        if FINISH_FUNCTIONS.intersection(names):
            return "finish"
        return "blend" if self._walked else "checks"

    def _record_sync(self, name: str) -> None:
        self.syncs[self._current_phase()].append(name)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if self._inside_launch:
            return func(*args, **(kwargs or {}))
        phase = self._current_phase()
        name = func.__name__
        self.ops[phase] += 1
        base = name.split(".")[0]
        self.kernels[phase] += base not in VIEW_OPS
        self.allocs += base in ALLOC_OPS
        self.op_names[phase][name] += 1
        if _is_sync(func, args):
            self.syncs[phase].append(name)
        return func(*args, **(kwargs or {}))


def launches(counter: OpCounter) -> int:
    """Kernel launches a GPU would make: aten ops that are neither views nor allocations, plus Triton kernels."""
    return counter.total_kernels - counter.allocs + counter.triton_launches


def launch_names(counter: OpCounter) -> Dict[str, int]:
    """The launching ops by name (aten and Triton), for messages."""
    names: Dict[str, int] = Counter()
    for per_phase in counter.op_names.values():
        for name, calls in per_phase.items():
            base = name.split(".")[0]
            if base not in VIEW_OPS and base not in ALLOC_OPS:
                names[name] += calls
    names.update(counter.triton_names)
    return dict(names)


def count_step(step: Callable[[], torch.Tensor]) -> OpCounter:
    """Runs ``step`` (forward, returns the loss) and its backward under an OpCounter."""
    with OpCounter() as counter:
        loss = step()
        with counter.phase("backward"):
            loss.backward()
    return counter


def model_step(levels: int, n: int, width: int, height: int, pixels: int):
    """VoteSplatModel.vote_loss_terms on a CPU-built model with random Gaussians, after project_for_votes; the
    step's batch (host tensors, as the datamanager gives them) is ``step.batch``."""
    import warnings

    from nerfstudio.data.scene_box import SceneBox

    from votesplat_ns.core.vote_maps import label_tensor, voting_pixels
    from votesplat_ns.ns.model import VoteSplatModelConfig
    from votesplat_ns.ns.rasterizer import project_for_votes

    names = tuple(f"level{i}" for i in range(levels))
    config = VoteSplatModelConfig(
        vote_levels=names,
        random_init=True,
        num_random=n,
        random_scale=2.0,
        num_downscales=0,
        vote_pixels_per_step=pixels,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = config.setup(
            scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1, -1], [1, 1, 1]])), num_train_data=1, metadata={}
        )
    model.train()
    model.step = 10_000
    focal = 0.8 * width
    K = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    viewmat = torch.eye(4)
    viewmat[2, 3] = 3.0
    with torch.no_grad():
        model.info = project_for_votes(
            model.means,
            model.quats,
            torch.exp(model.scales),
            torch.sigmoid(model.opacities).squeeze(-1),
            viewmat,
            K,
            width,
            height,
        )
    # Masks: a grid of rectangles per level (finer at later levels), label 0 = no mask on a border strip.
    labels = torch.zeros(levels, height, width, dtype=torch.int32)
    centroids = []
    for level in range(levels):
        cells = 2 + 2 * level
        ys = torch.arange(height)[:, None] * cells // height
        xs = torch.arange(width)[None, :] * cells // width
        labels[level] = (ys * cells + xs + 1).int()
        labels[level, :4] = 0
        table = torch.full((cells * cells + 1, 2), float("nan"))
        for label in range(1, cells * cells + 1):
            rows, cols = torch.nonzero(labels[level] == label, as_tuple=True)
            if len(rows):
                table[label] = torch.stack([cols.float().mean(), rows.float().mean()]).round()
        centroids.append(table)
    size = max(len(t) for t in centroids)
    centroids = torch.stack([torch.cat([t, torch.full((size - len(t), 2), float("nan"))]) for t in centroids])
    labels = label_tensor(labels.numpy())  # the datamanager's compact ids
    batch = {"vote_labels": labels, "vote_centroids": centroids, "vote_pixels": voting_pixels(labels, centroids)}

    def step(seed: Optional[int] = None):
        """The model's vote loss (vote + 0.05 distortion, the default weights); ``seed``: first restart the torch
        seed and the model's vote pixel draws there, as in a run seeded with it (the draws come from the model's
        own generator)."""
        if seed is not None:
            torch.manual_seed(seed)
            model._vote_pixel_generator = None  # made again at the next draw, from the seed
        model.gauss_params["vote_offsets"].grad = None
        loss, _terms = model.vote_loss_terms(batch)
        return loss

    step.batch = batch  # pyright: ignore[reportFunctionMemberAccess]
    return model, step
