"""Every change this plugin makes to code it does not own, in one place: what each changes and why.

They were written against nerfstudio 1.1.5 and gsplat 1.4.0 (:data:`WRITTEN_FOR`); :func:`apply`
warns once when an installed version differs, since any of them may then no longer fit.

Process-wide, applied by :func:`apply` when nerfstudio imports the method (every ``ns-*`` command):

* ``checkpoint safe globals`` (:func:`register_checkpoint_safe_globals`): adds the numpy types that
  nerfstudio 1.1.5 pickles into checkpoints to torch's ``weights_only`` allow-list (torch >= 2.6
  refuses them). Also applied on import of the package (``votesplat_ns/__init__.py``).
* ``one-line input errors`` (``votesplat_ns/errors.py`` ``install_excepthook``): wraps ``sys.excepthook``
  so that a ``VoteSplatInputError`` ends any ``ns-*`` command with one line instead of a traceback.
  Its body stays beside the error type, which every layer imports.
* ``ns-export votesplat-instances`` (:func:`install_ns_export_hook`): a meta-path finder that adds our
  subcommand to ``nerfstudio.scripts.exporter``'s command union while it is imported (nerfstudio
  has no plugin point for exporters).
* ``checkpoint checked first`` (:func:`install_checkpoint_check`): ``nerfstudio.utils.eval_utils.eval_setup``
  (``ns-viewer``, ``ns-eval``, ``ns-render``) first reads the run's config.yml with the plugin's safe loader and
  checks its checkpoint as the plugin's commands do, so a run without one ends in one line instead of nerfstudio's
  IndexError; a config.yml the safe loader refuses (another plugin's classes) is left to nerfstudio, as before.
* ``external methods listed cheaply`` (:func:`install_cheap_external_methods`): nerfstudio's
  ``ExternalMethodDummyTrainerConfig.__post_init__`` asks ``inspect.stack()`` whether ``get_external_methods`` made
  it, which reads the source lines of every frame and searches every loaded module for each: about a second of
  every ``ns-*`` command's start (each rank's, in a run of several), for its 26 entries. The same question is
  asked of the caller's frame directly; anything else goes to nerfstudio's own ``__post_init__``.

Scoped, applied where they are needed (listed here so that an upgrade checks them too):

* ``splatfacto rasterization`` (:func:`install_rasterizer_in_splatfacto`, when the model is built):
  rebinds ``nerfstudio.models.splatfacto.rasterization`` to ``ns/rasterizer.py`` ``rasterize``
  (torch rasteriser on CPU, cameras recorded for the vote pass).
* ``splatfacto get_viewmat untraced`` (:func:`install_untraced_viewmat`, when the model is built): its
  ``torch.compile``'d ``get_viewmat`` runs with the viewer's interrupt trace suspended, so a camera move during its
  first compilation cannot kill a render thread.
* ``Tensor.cuda on CPU`` (:func:`cuda_calls_stay_on_cpu`) and ``metrics at first use``
  (:func:`metrics_at_first_use`): context managers around nerfstudio code that calls ``.cuda()``
  unconditionally, or that imports torchmetrics (seconds) and downloads AlexNet to build metrics that
  most commands never call. :func:`splatfacto_metrics_at_first_use` applies the latter to stock splatfacto for
  the benchmarks that run it.
* ``resume trains`` (``ns/model.py``, ``load_state_dict`` / ``adopt_optimizers``): overrides in our
  model subclass, not a patch of upstream objects; nerfstudio builds the optimisers before loading a
  checkpoint and splatfacto replaces the parameters (#3554).
* gsplat's private ``cuda._torch_impl`` helpers (``core/rasterize_torch.py``, ``ns/retrofit.py``): used,
  not patched.
* ``safe resume`` (``ns/trainer.py`` ``VoteSplatTrainer``, the method's ``TrainerConfig._target``): a subclass
  whose ``_load_checkpoint`` reads with ``weights_only=True``, skips a half-written newest checkpoint and fails
  in one line, and whose ``train`` saves a checkpoint at Ctrl-C and exits 130 (nerfstudio's ``launch`` prints
  the ``KeyboardInterrupt`` and exits 0 with nothing saved); not a patch of ``Trainer``, so other methods keep
  nerfstudio's.

Left unpatched on purpose: nerfstudio's own reads of a config.yml with ``yaml.Loader`` (``eval_setup``, used
by ``ns-viewer``, ``ns-eval``, ``ns-render`` and ``ns-export``'s other exporters; ``ns-train --load-config``).
Our commands read it with ``ns/run_config.py`` instead. Swapping that loader in for every ``ns-*`` command
would refuse the config classes of every other installed plugin (the allow-list knows nerfstudio's and
ours), and swapping it in only for votesplat runs protects nothing: the file names its own method. README's
"Security" says what stays unsafe.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.abc
import sys
import threading
import types
import typing
import warnings
from dataclasses import dataclass
from importlib import metadata
from typing import Callable, Dict, Iterator, Tuple, Union

import numpy as np
import torch
from typing_extensions import Annotated

from votesplat_ns.errors import install_excepthook

WRITTEN_FOR: Dict[str, str] = {"nerfstudio": "1.1.5", "gsplat": "1.4.0"}


# ----------------------------------------------------------------------------- checkpoint safe globals


def register_checkpoint_safe_globals() -> None:
    """Let ``torch.load(weights_only=True)`` read nerfstudio checkpoints.

    torch >= 2.6 defaults to ``weights_only=True``; nerfstudio 1.1.5 calls ``torch.load``
    without the argument and its checkpoints hold numpy scalars (step counters, scheduler
    state), which the restricted unpickler refuses. Allow exactly those numpy types.
    """
    add = getattr(torch.serialization, "add_safe_globals", None)
    if add is None:  # torch < 2.4 loads everything anyway
        return
    numpy_types: list = [np.dtype, np.ndarray]
    try:
        from numpy.core.multiarray import _reconstruct, scalar  # type: ignore[attr-defined]
    except ImportError:  # numpy >= 2 keeps them in numpy._core
        from numpy._core.multiarray import _reconstruct, scalar  # type: ignore[no-redef]
    numpy_types += [scalar, _reconstruct]
    # numpy >= 1.25 pickles dtypes as instances of per-dtype classes (np.dtypes.Float64DType ...)
    dtypes_module = getattr(np, "dtypes", None)
    if dtypes_module is not None:
        numpy_types += [getattr(dtypes_module, name) for name in dir(dtypes_module) if name.endswith("DType")]
    add(numpy_types)


# ----------------------------------------------------------------------------- ns-export votesplat-instances

SUBCOMMAND_NAME = "votesplat-instances"
EXPORTER_MODULE = "nerfstudio.scripts.exporter"


def _extend_commands(exporter) -> bool:
    """Rebind exporter.Commands to nerfstudio's union plus our subcommand. False if not defined yet."""
    commands = exporter.__dict__.get("Commands")
    if commands is None:
        return False
    if getattr(exporter, "_votesplat_instances_hooked", False):
        return True
    import tyro

    # imported only when ns-export's commands are extended, not by every ns-* command that applies the patches
    from votesplat_ns.ns.export import ExportVoteSplatInstances

    markers: tuple = ()
    inner = commands
    if typing.get_origin(commands) is Annotated:
        inner, *rest = typing.get_args(commands)
        markers = tuple(rest)
    members = typing.get_args(inner) if typing.get_origin(inner) is Union else (inner,)
    ours = Annotated[ExportVoteSplatInstances, tyro.conf.subcommand(name=SUBCOMMAND_NAME)]
    extended = Union[tuple(members) + (ours,)]  # type: ignore[valid-type]
    exporter.Commands = Annotated[(extended, *markers)] if markers else extended
    exporter._votesplat_instances_hooked = True
    return True


class _ExporterBeingImported(types.ModuleType):
    """Module class swapped onto a half-imported exporter: extends Commands on first outside use.

    When the hook runs during nerfstudio's method discovery, ns-export is still executing
    exporter.py (Commands is defined further down). Module-level assignments go straight to the
    module dict, so we wait for the first attribute read from outside (the console script's
    ``from nerfstudio.scripts.exporter import entrypoint``), which happens after the import ends.
    """

    def __getattribute__(self, name: str):
        namespace = types.ModuleType.__getattribute__(self, "__dict__")
        if not name.startswith("__") and "Commands" in namespace:
            object.__setattr__(self, "__class__", types.ModuleType)
            _extend_commands(self)
        return types.ModuleType.__getattribute__(self, name)


class _PatchingLoader(importlib.abc.Loader):
    def __init__(self, inner, patch: Callable[[types.ModuleType], bool]):
        self._inner = inner
        self._patch = patch

    def create_module(self, spec):
        return self._inner.create_module(spec)

    def exec_module(self, module) -> None:
        self._inner.exec_module(module)
        self._patch(module)

    def __getattr__(self, name: str):
        return getattr(self._inner, name)


class _PatchingFinder(importlib.abc.MetaPathFinder):
    """Wraps the loader of module ``module_name`` so that ``patch(module)`` runs right after it executes."""

    def __init__(self, module_name: str, patch: Callable[[types.ModuleType], bool]):
        self.module_name = module_name
        self.patch = patch

    def find_spec(self, fullname, path, target=None):
        if fullname != self.module_name:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None and spec.loader is not None:
                spec.loader = _PatchingLoader(spec.loader, self.patch)
                return spec
        return None


class _ExporterFinder(_PatchingFinder):
    """Wraps the loader of the exporter module so Commands is extended right after it executes."""

    def __init__(self, module_name: str):
        super().__init__(module_name, _extend_commands)


def install_ns_export_hook(module_name: str = EXPORTER_MODULE) -> None:
    """Make ``ns-export votesplat-instances`` available (nerfstudio 1.1.5 has no exporter plugins).

    Cheap and idempotent; called by :func:`apply` from the plugin's method entry point module. ns-export
    imports nerfstudio.scripts.exporter, whose import of eval_utils -> method_configs discovers (imports)
    every method entry point *before* exporter.py defines Commands, so three cases are handled:
    exporter fully imported (extend now), half imported (extend on its first use from outside,
    see ``_ExporterBeingImported``), not imported yet (a meta-path finder extends it right after
    it executes; nothing heavy is imported here, so ns-train does not pay for open3d).
    ``module_name`` exists for tests.
    """
    exporter = sys.modules.get(module_name)
    if exporter is not None:
        if not _extend_commands(exporter) and type(exporter) is types.ModuleType:
            exporter.__class__ = _ExporterBeingImported
        return
    if not any(isinstance(f, _ExporterFinder) and f.module_name == module_name for f in sys.meta_path):
        sys.meta_path.insert(0, _ExporterFinder(module_name))


# ----------------------------------------------------------------------------- checkpoint checked first

EVAL_UTILS_MODULE = "nerfstudio.utils.eval_utils"


def _check_run_first(eval_utils: types.ModuleType) -> bool:
    """Rebind ``eval_utils.eval_setup`` to check the run's checkpoint before nerfstudio's. False if not defined yet."""
    original = eval_utils.__dict__.get("eval_setup")
    if original is None:
        return False
    if getattr(original, "_votesplat_checked", False):
        return True
    from pathlib import Path

    def eval_setup(config_path, *args, **kwargs):
        from votesplat_ns.errors import VoteSplatInputError
        from votesplat_ns.ns.run import checked_checkpoint
        from votesplat_ns.ns.run_config import load_run_config

        path = Path(config_path)
        if path.is_file():
            try:
                config = load_run_config(path)  # without running code: nerfstudio reads it again its own way
            except VoteSplatInputError:  # another plugin's config classes, or a file nerfstudio will judge itself
                config = None
            if config is not None:
                checked_checkpoint(config, path)  # one line for a run without a (loadable) checkpoint
        return original(config_path, *args, **kwargs)

    eval_setup._votesplat_checked = True  # type: ignore[attr-defined]
    eval_setup.__wrapped__ = original  # type: ignore[attr-defined]
    setattr(eval_utils, "eval_setup", eval_setup)  # noqa: B010  (typed as a plain module, whose import may be under way)
    return True


class _EvalUtilsBeingImported(types.ModuleType):
    """Module class swapped onto a half-imported eval_utils (it imports the method configs, which import us, before
    it defines eval_setup): rebinds eval_setup on the first attribute read from outside, once it exists."""

    def __getattribute__(self, name: str):
        namespace = types.ModuleType.__getattribute__(self, "__dict__")
        if not name.startswith("__") and "eval_setup" in namespace:
            object.__setattr__(self, "__class__", types.ModuleType)
            _check_run_first(self)
        return types.ModuleType.__getattribute__(self, name)


def install_checkpoint_check(module_name: str = EVAL_UTILS_MODULE) -> None:
    """Make ``ns-viewer`` (and every command on nerfstudio's ``eval_setup``: ``ns-eval``, ``ns-render``, ...) check
    the run's checkpoint before building the model, as the plugin's commands do: a run without one (training stopped
    before its first save) ends in one line instead of an IndexError. The same three cases as
    :func:`install_ns_export_hook`: eval_utils imported, half imported (the usual one: its import of the method
    configs imports the plugin), not imported yet."""
    eval_utils = sys.modules.get(module_name)
    if eval_utils is not None:
        if not _check_run_first(eval_utils) and type(eval_utils) is types.ModuleType:
            eval_utils.__class__ = _EvalUtilsBeingImported
        return
    if not any(isinstance(f, _PatchingFinder) and f.module_name == module_name for f in sys.meta_path):
        sys.meta_path.insert(0, _PatchingFinder(module_name, _check_run_first))


# ----------------------------------------------------------------------------- external methods listed cheaply

EXTERNAL_METHODS_MODULE = "nerfstudio.configs.external_methods"


def install_cheap_external_methods(module_name: str = EXTERNAL_METHODS_MODULE) -> None:
    """Make nerfstudio's list of not-installed methods cost microseconds instead of a second (module docstring).

    Its ``method_configs`` imports the method entry points (this plugin) before it calls ``get_external_methods``,
    so the patch is in place for that call. ``module_name`` exists for tests."""
    import importlib

    dummy = importlib.import_module(module_name).ExternalMethodDummyTrainerConfig
    original = dummy.__post_init__
    if getattr(original, "_votesplat_cheap", False):
        return

    def __post_init__(self) -> None:
        # nerfstudio asks inspect.stack()[2].function: frame 0 is this method, 1 the dataclass's __init__, 2 its caller
        if sys._getframe(2).f_code.co_name == "get_external_methods":
            return
        original(self)  # made from the command line: nerfstudio offers to install the method

    __post_init__._votesplat_cheap = True  # type: ignore[attr-defined]
    __post_init__.__wrapped__ = original  # type: ignore[attr-defined]
    dummy.__post_init__ = __post_init__


# ----------------------------------------------------------------------------- splatfacto rasterization

_rasterizer_lock = threading.Lock()


def install_rasterizer_in_splatfacto() -> None:
    """Point ``nerfstudio.models.splatfacto.rasterization`` at ``ns/rasterizer.py`` ``rasterize`` (idempotent).

    splatfacto calls that module-level name; gsplat's own ``rasterization`` JIT-builds CUDA code and
    cannot run on CPU, and the vote pass needs the cameras splatfacto rendered with (see
    :func:`votesplat_ns.ns.rasterizer.rasterize`). Rebound once, under a lock, not per call, because
    the viewer renders from another thread.
    """
    import nerfstudio.models.splatfacto as splatfacto_module

    from votesplat_ns.ns.rasterizer import rasterize

    with _rasterizer_lock:
        if getattr(splatfacto_module, "rasterization", None) is not rasterize:
            # the module's own import of gsplat's function, replaced as a name of that module
            setattr(splatfacto_module, "rasterization", rasterize)


def install_untraced_viewmat() -> None:
    """Point ``nerfstudio.models.splatfacto.get_viewmat`` at :func:`untraced` of itself (idempotent; under the
    rasterizer's lock, as the viewer renders from another thread)."""
    import nerfstudio.models.splatfacto as splatfacto_module

    with _rasterizer_lock:
        if not getattr(splatfacto_module.get_viewmat, "votesplat_untraced", False):
            setattr(splatfacto_module, "get_viewmat", untraced(splatfacto_module.get_viewmat))


def untraced(function: Callable) -> Callable:
    """``function`` called with the calling thread's trace function (``sys.settrace``) suspended.

    splatfacto's ``get_viewmat`` is ``torch.compile``'d and compiles on its first call. The viewer's render threads
    run under a per-line trace that raises ``IOChangeException`` when the camera moves; raised while dynamo traces
    ``get_viewmat``, it becomes an ``InternalTorchDynamoError`` that kills the render thread, and the page never
    updates again (CI saw it once, a browser connected while the viewer was still being built). Suspending the trace
    for the call covers every thread and every first call, so nothing compiles it ahead. The interrupt is checked
    again on the render's next line.
    """

    def call(*args, **kwargs):
        trace = sys.gettrace()
        if trace is None:
            return function(*args, **kwargs)
        sys.settrace(None)
        try:
            return function(*args, **kwargs)
        finally:
            sys.settrace(trace)

    call.votesplat_untraced = True  # pyright: ignore[reportFunctionMemberAccess]
    call.__wrapped__ = function  # pyright: ignore[reportFunctionMemberAccess]
    return call


# ----------------------------------------------------------------------------- Tensor.cuda on CPU

_cuda_patch_lock = threading.Lock()
_cuda_patch_depth = 0
_original_tensor_cuda = torch.Tensor.cuda


def _tensor_stays_put(self: torch.Tensor, *args, **kwargs) -> torch.Tensor:
    return self


@contextlib.contextmanager
def cuda_calls_stay_on_cpu(model_on_cpu: bool = False) -> Iterator[None]:
    """Make ``Tensor.cuda()`` a no-op inside the block when no CUDA device exists, or always when
    ``model_on_cpu`` (a model kept on the CPU of a CUDA machine, e.g. ``--machine.device-type cpu``).

    splatfacto hard-codes ``.cuda()`` in ``populate_modules`` and ``get_outputs``; on a CPU-only
    machine we run its code unchanged (rather than copying it) and keep tensors where they are.
    Reference-counted under a lock because the viewer renders from another thread while
    training runs: the real method comes back only when the last block exits.
    """
    global _cuda_patch_depth
    if torch.cuda.is_available() and not model_on_cpu:
        yield
        return
    with _cuda_patch_lock:
        _cuda_patch_depth += 1
        torch.Tensor.cuda = _tensor_stays_put  # type: ignore[method-assign]
    try:
        yield
    finally:
        with _cuda_patch_lock:
            _cuda_patch_depth -= 1
            if _cuda_patch_depth == 0:
                torch.Tensor.cuda = _original_tensor_cuda  # type: ignore[method-assign]


# ----------------------------------------------------------------------------- splatfacto's metrics at first use

# the modules splatfacto's populate_modules imports its metrics from, and the names it takes
_METRIC_MODULES = {
    "torchmetrics.image": "PeakSignalNoiseRatio",
    "torchmetrics.image.lpip": "LearnedPerceptualImagePatchSimilarity",
}
_STAND_IN_DOC = "stands in for torchmetrics within votesplat_ns.ns.patches.metrics_at_first_use"


def _torchmetrics_class(module_name: str, attribute: str):
    """torchmetrics' own ``module_name.attribute``, imported now, also when a block is still open (a metric called
    inside one): its stand-in modules give way to the real package, and a name a block replaced on it is followed
    back to the class it replaced."""
    for name in ("torchmetrics", *_METRIC_MODULES):
        if getattr(sys.modules.get(name), "__doc__", None) == _STAND_IN_DOC:
            del sys.modules[name]
    found = getattr(importlib.import_module(module_name), attribute)
    while hasattr(found, "replaced"):
        found = found.replaced
    return found


@contextlib.contextmanager
def metrics_at_first_use() -> Iterator[None]:
    """Within the block, splatfacto's PSNR and LPIPS are made as :class:`votesplat_ns.ns.compat.MetricAtFirstUse`.

    splatfacto's ``populate_modules`` imports them from torchmetrics and builds them, which costs torchmetrics'
    package import (seconds, see ``MetricAtFirstUse``) and downloads AlexNet for LPIPS. Inside the block both
    names give a metric built at its first call: PSNR as splatfacto asked for it, LPIPS through
    :func:`votesplat_ns.ns.compat.make_lpips_metric` (the local weights, or a NaN-reporting stand-in, never a
    download). Where torchmetrics is not imported yet, stand-in modules that hold only those two names take its
    place in ``sys.modules`` for the block, so that it is not imported (any other import of torchmetrics inside
    the block would fail: keep the block to ``populate_modules``); where it is, the two names are replaced on it
    for the block.
    """
    from votesplat_ns.ns.compat import MetricAtFirstUse, make_lpips_metric

    def psnr(*args, **kwargs):
        return MetricAtFirstUse(
            lambda: _torchmetrics_class("torchmetrics.image", "PeakSignalNoiseRatio")(*args, **kwargs)
        )

    def lpips(*args, **kwargs):  # splatfacto asks for normalize=True, which make_lpips_metric builds
        return MetricAtFirstUse(make_lpips_metric)

    factories = dict(zip(_METRIC_MODULES, (psnr, lpips)))
    stand_ins = {}
    replaced = []
    if "torchmetrics" not in sys.modules:
        for name in ("torchmetrics", *_METRIC_MODULES):
            stand_ins[name] = sys.modules[name] = types.ModuleType(name, _STAND_IN_DOC)
            if name in factories:
                setattr(stand_ins[name], _METRIC_MODULES[name], factories[name])
    else:
        for name, attribute in _METRIC_MODULES.items():
            module = importlib.import_module(name)
            factories[name].replaced = getattr(module, attribute)  # type: ignore[attr-defined]
            replaced.append((module, attribute, factories[name].replaced))  # type: ignore[attr-defined]
            setattr(module, attribute, factories[name])
    try:
        yield
    finally:
        for name, module in stand_ins.items():
            if sys.modules.get(name) is module:  # not if a metric called inside the block imported the real one
                del sys.modules[name]
        for module, attribute, original in replaced:
            setattr(module, attribute, original)


@contextlib.contextmanager
def splatfacto_metrics_at_first_use() -> Iterator[None]:
    """Within the block, every splatfacto model built (nerfstudio's own ``splatfacto`` too) builds its metrics under
    :func:`metrics_at_first_use`: for the benchmarks that run stock splatfacto beside votesplat, offline and alike
    (votesplat's ``populate_modules`` opens its own block; blocks nest). Only ``populate_modules`` runs inside
    :func:`metrics_at_first_use`, so the rest of the block may import torchmetrics."""
    from nerfstudio.models.splatfacto import SplatfactoModel

    populate_modules = SplatfactoModel.populate_modules

    def populate_modules_with_metrics_at_first_use(self):
        with metrics_at_first_use():
            populate_modules(self)

    SplatfactoModel.populate_modules = populate_modules_with_metrics_at_first_use  # type: ignore[method-assign]
    try:
        yield
    finally:
        SplatfactoModel.populate_modules = populate_modules  # type: ignore[method-assign]


# ----------------------------------------------------------------------------- the list and apply()


@dataclass(frozen=True)
class Patch:
    name: str
    changes: str
    install: Callable[[], None]


PATCHES: Tuple[Patch, ...] = (
    Patch("checkpoint safe globals", "torch.serialization's weights_only allow-list", register_checkpoint_safe_globals),
    Patch("one-line input errors", "sys.excepthook", install_excepthook),
    Patch(
        "ns-export votesplat-instances",
        "nerfstudio.scripts.exporter's Commands (meta-path finder)",
        install_ns_export_hook,
    ),
    Patch("checkpoint checked first", "nerfstudio.utils.eval_utils.eval_setup", install_checkpoint_check),
    Patch(
        "external methods listed cheaply",
        "nerfstudio.configs.external_methods.ExternalMethodDummyTrainerConfig.__post_init__",
        install_cheap_external_methods,
    ),
)

_version_warned = False


def version_mismatches() -> Dict[str, Tuple[str, str]]:
    """{package: (installed, written for)} for every package whose installed version differs."""
    found = {}
    for package, expected in WRITTEN_FOR.items():
        try:
            installed = metadata.version(package)
        except metadata.PackageNotFoundError:
            installed = "not installed"
        if installed != expected:
            found[package] = (installed, expected)
    return found


def apply() -> None:
    """Apply the process-wide patches (idempotent); a failing patch warns and the others still apply."""
    global _version_warned
    mismatches = version_mismatches()
    if mismatches and not _version_warned:
        _version_warned = True
        listed = ", ".join(f"{name} {have} (written for {want})" for name, (have, want) in mismatches.items())
        warnings.warn(
            f"votesplat: {listed}; the plugin's patches (votesplat_ns/ns/patches.py) may not fit", RuntimeWarning
        )
    for patch in PATCHES:
        try:
            patch.install()
        except Exception as err:  # one broken patch must not break every ns-* command
            warnings.warn(f"votesplat: patch {patch.name!r} ({patch.changes}) not applied: {err}", RuntimeWarning)
