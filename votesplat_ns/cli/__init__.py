"""The ``votesplat <subcommand>`` command line (main), its subcommands' options (query_cli, evaluate_cli,
masks_cli; ``export`` lives in ns/export.py and ``synth`` in eval/synthetic/cli.py) and the shared
one-line error reporting (cli_errors). The old ``votesplat-*`` scripts are aliases of the subcommands.
"""
