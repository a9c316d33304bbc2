"""A run's config.yml, read without running code.

nerfstudio writes a run's ``TrainerConfig`` with ``yaml.dump`` (a Python object dump: ``!!python/object``
config dataclasses, ``!!python/name`` classes for their ``_target``, ``!!python/object/apply`` paths and
enums, ``!!python/tuple``) and reads it back with ``yaml.Loader``, which builds whatever the file names:
``!!python/object/apply:os.system [...]`` runs a command while the file loads. :class:`RunConfigLoader`
is a ``yaml.SafeLoader`` that builds only what such a dump holds, from an allow-list:

* ``!!python/object:M.C``: a dataclass ``C`` defined in a module under ``nerfstudio.`` or ``votesplat_ns.``,
  made as ``yaml.Loader`` makes it (``__new__``, then its fields set) and so equal to what it would give;
  a key that names a method or other class attribute that is not a field is refused;
* ``!!python/name:M.C``: a class (never a function) defined under ``nerfstudio.`` or ``votesplat_ns.``, or
  a torch optimizer or learning-rate scheduler class (a config's ``_target``);
* ``!!python/object/apply:pathlib.PosixPath`` (and the other ``pathlib`` path classes) of strings, and
  ``!!python/object/apply:M.E [value]`` for an ``Enum`` ``E`` under ``nerfstudio.`` or ``votesplat_ns.``;
* ``!!python/tuple``.

A class named under a module of an earlier votesplat_ns layout (:data:`MOVED_MODULES`) is looked up where it lives
now, so runs trained before a move still open.

Anything else (another module, a function, ``!!python/object/apply`` of anything but a path or an enum,
``!!python/object/new``, ``!!python/module``, an unknown tag) raises :class:`RefusedTag`, which
:func:`load_run_config` turns into one line naming the file, the tag and its line.
"""

from __future__ import annotations

import dataclasses
import enum
import importlib
import os
import pathlib
from pathlib import Path
from typing import Any, Dict, Iterator, Optional, Tuple, Union

import yaml
from yaml.constructor import ConstructorError
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from votesplat_ns.errors import VoteSplatInputError

ALLOWED_PACKAGES: Tuple[str, ...] = ("nerfstudio", "votesplat_ns")
PATH_CLASSES = {
    f"pathlib.{cls.__name__}": cls
    for cls in (pathlib.Path, pathlib.PosixPath, pathlib.WindowsPath, pathlib.PurePath, pathlib.PurePosixPath)
}
PATH_CLASSES["pathlib.PureWindowsPath"] = pathlib.PureWindowsPath
YAML_PREFIX = "tag:yaml.org,2002:"
# modules of an earlier votesplat_ns layout that config.yml files of older runs name: where their classes live now
MOVED_MODULES: Dict[str, str] = {
    "votesplat_ns.model": "votesplat_ns.ns.model",
    "votesplat_ns.datamanager": "votesplat_ns.ns.datamanager",
    "votesplat_ns.ns.model_config": "votesplat_ns.ns.model",
}
WHAT_IS_ALLOWED = "a run's config.yml may hold only nerfstudio and votesplat config classes, paths, enums and tuples"


class RefusedTag(ConstructorError):
    """A tag :class:`RunConfigLoader` does not build: ``tag`` (as written in the file) at ``line``, and why."""

    def __init__(self, tag: str, node: Node, why: str, other_version: bool = False):
        self.tag = "!!" + tag[len(YAML_PREFIX) :] if tag.startswith(YAML_PREFIX) else tag  # as written in the file
        self.line = node.start_mark.line + 1
        self.why = why
        # a nerfstudio or votesplat class this installation does not have: a run of another version, not a payload
        self.other_version = other_version
        super().__init__(None, None, f"refused tag {self.tag} ({why})", node.start_mark)


def _in_allowed_package(module_name: str, packages: Tuple[str, ...] = ALLOWED_PACKAGES) -> bool:
    return any(module_name == package or module_name.startswith(package + ".") for package in packages)


def _allowed_class(name: str, node: Node, tag: str, packages: Tuple[str, ...] = ALLOWED_PACKAGES) -> type:
    """The class ``module.Name`` names, when its module and the module that defines it are in ``packages``."""
    module_name, _, attribute = name.rpartition(".")
    if not module_name or not _in_allowed_package(module_name, packages):
        raise RefusedTag(tag, node, f"module {module_name or name!r} is not nerfstudio's or votesplat's")
    try:
        module = importlib.import_module(MOVED_MODULES.get(module_name, module_name))
    except ImportError:
        raise RefusedTag(tag, node, f"module {module_name} is not installed here", other_version=True) from None
    found = getattr(module, attribute, None)
    if found is None:
        raise RefusedTag(tag, node, f"{module_name} has no {attribute} here", other_version=True)
    if not isinstance(found, type):
        raise RefusedTag(tag, node, f"{name} is not a class")
    if not _in_allowed_package(found.__module__, packages):  # e.g. a name a nerfstudio module imported
        raise RefusedTag(tag, node, f"{name} is defined in {found.__module__}")
    return found


def _torch_scheduling_class(name: str) -> Optional[type]:
    """A torch optimizer or learning-rate scheduler class named ``torch.optim....``, else None."""
    if not name.startswith("torch.optim."):
        return None
    import torch

    module_name, _, attribute = name.rpartition(".")
    try:
        found = getattr(importlib.import_module(module_name), attribute, None)
    except ImportError:
        return None
    bases = (torch.optim.Optimizer, torch.optim.lr_scheduler.LRScheduler)
    return found if isinstance(found, type) and issubclass(found, bases) else None


def _construct_object(loader: "RunConfigLoader", suffix: str, node: Node) -> Iterator[Any]:
    tag = node.tag
    cls = _allowed_class(suffix, node, tag)
    if not dataclasses.is_dataclass(cls):
        raise RefusedTag(tag, node, f"{suffix} is not a config dataclass")
    if not isinstance(node, MappingNode):
        raise RefusedTag(tag, node, "a config object must be a mapping of its fields")
    instance = cls.__new__(cls)
    yield instance
    state = loader.construct_mapping(node, deep=True)
    fields = {field.name for field in dataclasses.fields(cls)}
    values: Dict[str, Any] = {}
    for key, value in state.items():
        # a key that is no field may be one an older nerfstudio wrote, but never one that hides a method
        if not isinstance(key, str) or key.startswith("__") or (key not in fields and hasattr(cls, key)):
            raise RefusedTag(tag, node, f"{key!r} is not a field of {suffix}")
        values[key] = value
    instance.__dict__.update(values)


def _construct_name(loader: "RunConfigLoader", suffix: str, node: Node) -> type:
    tag = node.tag
    if not isinstance(node, ScalarNode) or loader.construct_scalar(node):
        raise RefusedTag(tag, node, "a class name takes no value")
    found = _torch_scheduling_class(suffix)
    return found if found is not None else _allowed_class(suffix, node, tag)


def _scalars(loader: "RunConfigLoader", node: Node, tag: str) -> list:
    if not isinstance(node, SequenceNode) or not all(isinstance(item, ScalarNode) for item in node.value):
        raise RefusedTag(tag, node, "only a list of plain values is allowed here")
    return loader.construct_sequence(node)


def _construct_apply(loader: "RunConfigLoader", suffix: str, node: Node) -> Any:
    tag = node.tag
    if suffix in PATH_CLASSES:
        parts = _scalars(loader, node, tag)
        if not all(isinstance(part, str) for part in parts):
            raise RefusedTag(tag, node, "a path is made of strings")
        return PATH_CLASSES[suffix](*parts)
    cls = _allowed_class(suffix, node, tag)
    if not issubclass(cls, enum.Enum):
        raise RefusedTag(tag, node, f"{suffix} is neither a path nor an enum: calling it could run code")
    values = _scalars(loader, node, tag)
    if len(values) != 1:
        raise RefusedTag(tag, node, "an enum member is given by one value")
    try:
        return cls(values[0])
    except ValueError:
        raise RefusedTag(tag, node, f"{values[0]!r} is not a member of {suffix}") from None


def _construct_tuple(loader: "RunConfigLoader", node: Node) -> tuple:
    if not isinstance(node, SequenceNode):
        raise RefusedTag(node.tag, node, "a tuple must be a list")
    return tuple(loader.construct_sequence(node, deep=True))


def _refuse(loader: "RunConfigLoader", node: Node) -> Any:
    raise RefusedTag(node.tag, node, "not a tag of a nerfstudio config")


class RunConfigLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` plus the tags of a nerfstudio run's config.yml, from the allow-list above."""


RunConfigLoader.add_multi_constructor(YAML_PREFIX + "python/object:", _construct_object)
RunConfigLoader.add_multi_constructor(YAML_PREFIX + "python/name:", _construct_name)
RunConfigLoader.add_multi_constructor(YAML_PREFIX + "python/object/apply:", _construct_apply)
RunConfigLoader.add_constructor(YAML_PREFIX + "python/tuple", _construct_tuple)
# every other tag, with the same one-line refusal (None: PyYAML's key for "no constructor of its own")
RunConfigLoader.add_constructor(None, _refuse)  # pyright: ignore[reportArgumentType]


def parse_run_config(text: str) -> Any:
    """The object a config.yml's ``text`` holds, built by :class:`RunConfigLoader` (raises :class:`RefusedTag`)."""
    return yaml.load(text, Loader=RunConfigLoader)  # noqa: S506 - a SafeLoader with an allow-list


def refusal_message(load_config: Union[str, Path], flag: str, refused: RefusedTag) -> str:
    """The one line for a config.yml whose ``refused`` tag could run code, or names a class of another version."""
    if refused.other_version:
        return (
            f"{flag} {load_config}: line {refused.line} names {refused.tag}, which this installation does not have "
            f"({refused.why}): the run was written by another version of votesplat_ns or nerfstudio; open it with "
            "the version that trained it, or train it again with this one"
        )
    return (
        f"{flag} {load_config}: refused to load tag {refused.tag} at line {refused.line} ({refused.why}): "
        f"{WHAT_IS_ALLOWED}, and this file could run code when loaded; do not open it with nerfstudio either "
        "(ns-viewer, ns-eval); ask for a config.yml written by ns-train"
    )


def load_run_config(load_config: Union[str, Path], flag: str = "--load-config") -> Any:
    """A run's config.yml as nerfstudio wrote it (its ``TrainerConfig``), built without running code.

    A missing file, a file that is not a nerfstudio run config, or a tag outside the allow-list raise
    :class:`VoteSplatInputError` naming ``flag`` and the file (for a tag: the tag and its line).
    """
    from nerfstudio.engine.trainer import TrainerConfig

    load_config = Path(load_config)
    if not load_config.is_file():
        raise VoteSplatInputError(
            f"{flag} {load_config}: file not found; pass the config.yml of a votesplat run (outputs/.../config.yml)"
        )
    try:
        text = load_config.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise not_a_run_config(load_config, flag, error) from None
    except OSError as error:  # no permission to read it, ...
        raise VoteSplatInputError(
            f"{flag} {load_config}: cannot be read ({error.strerror or type(error).__name__}); "
            "make it readable (e.g. chmod a+r), or pass another run"
        ) from None
    if not text.strip():
        raise VoteSplatInputError(
            f"{flag} {load_config}: the file is empty; pass the config.yml that ns-train wrote (or train the run again)"
        )
    try:
        config = parse_run_config(text)
    except RefusedTag as refused:
        raise VoteSplatInputError(refusal_message(load_config, flag, refused)) from None
    except yaml.YAMLError as error:
        raise not_a_run_config(load_config, flag, error) from None
    if not isinstance(config, TrainerConfig):
        raise not_a_run_config(load_config, flag, TypeError(type(config).__name__))
    anchor_to_run_folder(config, load_config)
    return config


# paths of a run config that ns-train keeps as given, relative to the folder it ran in: (owner, field)
RELATIVE_INPUTS = (
    ("", "data"),
    ("pipeline.datamanager", "data"),
    ("pipeline.datamanager", "mask_folder"),
    ("pipeline.datamanager", "sam_checkpoint"),
    ("pipeline.model", "retrofit_from"),
)


def _owner(config: Any, dotted: str) -> Any:
    for name in filter(None, dotted.split(".")):
        config = getattr(config, name, None)
    return config


def training_folder(config: Any, load_config: Union[str, Path]) -> Optional[Path]:
    """The folder ns-train ran in, when the run's ``output_dir`` is relative and its config.yml lies where
    ns-train put it (``<that folder>/<output_dir>/<experiment>/<method>/<timestamp>/config.yml``); else None."""
    run_dir = Path(os.path.abspath(Path(load_config).parent))
    output_dir = Path(config.output_dir)
    tail = (str(config.experiment_name), str(config.method_name), str(config.timestamp))
    if output_dir.is_absolute() or ".." in output_dir.parts or run_dir.parts[-3:] != tail:
        return None
    root = run_dir.parents[2]
    count = len(output_dir.parts)
    if count and root.parts[-count:] != output_dir.parts:
        return None
    return Path(*root.parts[: len(root.parts) - count]) if count else root


def anchor_to_run_folder(config: Any, load_config: Union[str, Path]) -> None:
    """Point a run config at the run its config.yml belongs to, from whatever folder the command runs in.

    * The checkpoints are those beside the config.yml: ``output_dir`` becomes the folder above the run's
      ``<experiment>/<method>/<timestamp>`` (or, in a folder that was renamed, ``relative_model_dir`` becomes the
      run folder's own). ns-train often writes ``output_dir`` relative (``outputs``), which nerfstudio reads from the
      current folder; a moved run's absolute one names where it was.
    * Inputs given relative to the folder ns-train ran in (``--data data/scene``), found from there but not from
      the current folder, are made absolute; so is the default vote cache (``outputs/<dataset>/votesplat_cache``
      under that folder), so that the command reads the run's cache instead of making another one here.
    """
    run_dir = Path(os.path.abspath(Path(load_config).parent))
    if config.experiment_name is not None and run_dir.parts[-3:] == (
        str(config.experiment_name),
        str(config.method_name),
        str(config.timestamp),
    ):
        trained_in = training_folder(config, load_config)
        config.output_dir = run_dir.parents[2]
    else:
        trained_in = None
        config.relative_model_dir = run_dir / config.relative_model_dir
    if trained_in is None or trained_in == Path.cwd().resolve():
        return
    for owner_name, field in RELATIVE_INPUTS:
        owner = _owner(config, owner_name)
        value = getattr(owner, field, None)
        if isinstance(value, Path) and not value.is_absolute() and not value.exists() and (trained_in / value).exists():
            setattr(owner, field, trained_in / value)
    datamanager = _owner(config, "pipeline.datamanager")
    if hasattr(datamanager, "cache_dir"):
        cache_dir = datamanager.cache_dir
        if cache_dir is None and datamanager.data is not None:
            from votesplat_ns.ns.data_checks import default_cache_dir

            datamanager.cache_dir = trained_in / default_cache_dir(Path(datamanager.data))
        elif isinstance(cache_dir, Path) and not cache_dir.is_absolute():
            datamanager.cache_dir = trained_in / cache_dir


def not_a_run_config(load_config: Path, flag: str, error: BaseException) -> VoteSplatInputError:
    return VoteSplatInputError(
        f"{flag} {load_config}: not a nerfstudio run config ({type(error).__name__}); pass the config.yml that ns-train wrote"
    )
