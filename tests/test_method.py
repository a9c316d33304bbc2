"""The votesplat method is found through nerfstudio's plugin registry, is well formed and its help is findable."""

import dataclasses
import os
import re
import subprocess
import sys
from pathlib import Path

from nerfstudio.plugins.registry import discover_methods

from votesplat_ns.ns.method import VOTESPLAT_DESCRIPTION
from votesplat_ns.ns.model import VOTE_PARAM_NAMES, VoteSplatModelConfig


def test_votesplat_is_discovered_through_the_entry_point():
    methods, descriptions = discover_methods()
    assert "votesplat" in methods
    config = methods["votesplat"]
    assert config.method_name == "votesplat"
    assert isinstance(config.pipeline.model, VoteSplatModelConfig)
    assert "VoteSplat" in descriptions["votesplat"]


def test_every_gaussian_parameter_group_has_an_optimizer():
    # splatfacto's strategy densifies/prunes a gauss_params entry only if it has an optimizer.
    config = discover_methods()[0]["votesplat"]
    for name in ("means", "scales", "quats", "features_dc", "features_rest", "opacities", *VOTE_PARAM_NAMES):
        assert name in config.optimizers, name


def own_fields(cls, base) -> dict:
    """The dataclass fields ``cls`` adds to ``base`` (in ``cls`` or an options class it also derives from,
    e.g. ``SamOptions``), with the docstring under each (None if missing)."""
    import ast
    import inspect
    import textwrap

    docstrings = {}
    for klass in cls.__mro__:
        if klass is object or issubclass(base, klass):
            continue
        body = ast.parse(textwrap.dedent(inspect.getsource(klass))).body[0].body
        for statement, following in zip(body, body[1:] + [None]):
            if isinstance(statement, ast.AnnAssign) and isinstance(statement.target, ast.Name):
                is_doc = (
                    isinstance(following, ast.Expr)
                    and isinstance(following.value, ast.Constant)
                    and isinstance(following.value.value, str)
                )
                docstrings.setdefault(statement.target.id, following.value.value if is_doc else None)
    inherited = {f.name for f in dataclasses.fields(base)}
    return {name: doc for name, doc in docstrings.items() if name not in inherited and not name.startswith("_")}


def test_own_options_have_short_complete_docstrings():
    # tyro keeps a docstring's line breaks (a continuation line is indented), so one line each: no ragged help
    from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanagerConfig
    from nerfstudio.models.splatfacto import SplatfactoModelConfig

    from votesplat_ns.ns.datamanager import VoteDataManagerConfig

    for cls, base in (
        (VoteDataManagerConfig, FullImageDatamanagerConfig),
        (VoteSplatModelConfig, SplatfactoModelConfig),
    ):
        fields = own_fields(cls, base)
        assert len(fields) >= 10
        for name, doc in fields.items():
            assert doc and "\n" not in doc and doc.rstrip().endswith((".", ")")), f"{cls.__name__}.{name}: {doc!r}"


def test_help_starts_by_naming_the_methods_own_options():
    # a new interpreter, not a preloaded runner's fork: the help is laid out for 100 columns (its first 20 lines
    # must name the options), and the shared runners run under COLUMNS=200 (conftest.py command_env)
    env = dict(os.environ, COLUMNS="100", PYTHONWARNINGS="ignore")
    result = subprocess.run(
        [str(Path(sys.executable).parent / "ns-train"), "votesplat", "--help"],
        capture_output=True,
        check=False,
        text=True,
        env=env,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    lines = [line.strip(" │") for line in result.stdout.splitlines()]  # tyro's boxes
    top = " ".join(lines[:20])
    for words in (
        "--pipeline.model.vote-start-step",
        "--pipeline.datamanager.mask-source",
        "--pipeline.model.retrofit-from",
        "'Troubleshooting'",
    ):
        assert words in top, top
    # every option and README section the description names exists
    named_flags = set(re.findall(r"--pipeline\.[a-z.-]+[a-z]", VOTESPLAT_DESCRIPTION))
    assert len(named_flags) >= 7
    for flag in named_flags - {"--pipeline.model.vote"}:  # "--pipeline.model.vote-* options" names a family
        assert any(line.startswith(flag + " ") for line in lines[20:]), flag
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    for section in re.findall(r"'([^']+)'", VOTESPLAT_DESCRIPTION):
        assert re.search(rf"^#+ {re.escape(section)}$", readme, re.MULTILINE), section
