"""The ``votesplat`` command: one entry point for the plugin's tools, one error path.

    votesplat masks        --data D [...]                      masks and 2D votes without training (§3.2)
    votesplat export       --load-config C --output-dir D      instances as PLY files (§3.4)
    votesplat query        --load-config C "red mug" [...]     open-vocabulary selection
    votesplat click        --load-config C --view V --x X --y Y --output-dir D
    votesplat query-eval   --load-config C --labels L          LERF-OVS style selection score
    votesplat eval         --load-config C [...]               instance scores on a synthetic scene
    votesplat noisy-masks  --data D --output O                 GT masks with SAM-like errors
    votesplat synth        RECIPE --output-dir D [...]         render a synthetic scene (also: synth family-set)
    votesplat write-labels --scene S --output-dir L            LERF-OVS labels from GT masks

Bad input (``ValueError``, which :class:`~votesplat_ns.errors.VoteSplatInputError` is, and a
missing optional package) ends every subcommand the same way: one line ``votesplat <sub>: error: ...``
on stderr and exit status 1, no traceback. ``ns-train votesplat``, ``ns-viewer`` and ``ns-export
votesplat-instances`` are nerfstudio's own commands and unchanged.
"""

from __future__ import annotations

import sys
from typing import Any, Dict, Optional, Sequence, Union

import tyro
from typing_extensions import Annotated

from votesplat_ns.cli import evaluate_cli, masks_cli, query_cli
from votesplat_ns.errors import one_line_errors
from votesplat_ns.eval.synthetic import cli as synth_cli
from votesplat_ns.ns.export import ExportVoteSplatInstances

# subcommand -> (options dataclass, whether booleans take a value as before: --overwrite True)
COMMANDS: Dict[str, Any] = {
    "masks": (masks_cli.MasksConfig, False),
    "export": (ExportVoteSplatInstances, True),
    "query": (query_cli.Query, False),
    "click": (query_cli.Click, False),
    "query-eval": (query_cli.QueryEval, False),
    "eval": (evaluate_cli.EvaluateVoteSplat, True),
    "noisy-masks": (evaluate_cli.WriteNoisyMasks, True),
    "write-labels": (query_cli.WriteLabels, False),
}
SYNTH = "synth"
SUBCOMMANDS = (*COMMANDS, SYNTH)
# what ends a command with one line instead of a traceback
INPUT_ERRORS = (ValueError, ImportError)


def _annotated(cls: type, flags_take_values: bool) -> Any:
    return tyro.conf.FlagConversionOff[cls] if flags_take_values else cls


def _run(command: Any) -> Any:
    if isinstance(command, masks_cli.MasksConfig):
        return masks_cli.main(command)
    if hasattr(command, "run"):
        return command.run()
    return command.main()


def main(args: Optional[Sequence[str]] = None) -> Any:
    """Parse ``args`` (default: sys.argv[1:]) and run the subcommand."""
    args = list(sys.argv[1:] if args is None else args)
    tyro.extras.set_accent_color("bright_yellow")
    name = args[0] if args and args[0] in SUBCOMMANDS else None
    prog = f"votesplat {name}" if name else "votesplat"
    if name == SYNTH:
        with one_line_errors(catch=INPUT_ERRORS, prog=prog):
            return synth_cli.main(args[1:], prog=prog)
    if name is not None:
        cls, flags_take_values = COMMANDS[name]
        command = tyro.cli(_annotated(cls, flags_take_values), args=args[1:], prog=prog)
    else:  # no or an unknown subcommand: tyro lists the subcommands
        # a Union built at run time from COMMANDS: no static type describes it
        subcommands: Any = Union[
            tuple(  # type: ignore[misc]
                Annotated[_annotated(cls, flags), tyro.conf.subcommand(name=key)]
                for key, (cls, flags) in COMMANDS.items()
            )
        ]
        description = f"VoteSplat tools; also 'votesplat {SYNTH} --help' (render a synthetic scene with exact labels)."
        command = tyro.cli(subcommands, args=args, prog="votesplat", description=description)
        name = next(key for key, (cls, _) in COMMANDS.items() if isinstance(command, cls))
        prog = f"votesplat {name}"
    with one_line_errors(catch=INPUT_ERRORS, prog=prog):
        return _run(command)


def entrypoint() -> None:
    """Console script ``votesplat``."""
    main()
