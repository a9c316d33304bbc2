"""The ``votesplat <subcommand>`` command line (main) and its subcommands' options (query_cli, evaluate_cli,
masks_cli; ``export`` lives in ns/export.py and ``synth`` in eval/synthetic/cli.py). Its one-line errors
are those of every ns-* command (``votesplat_ns/errors.py``).
"""
