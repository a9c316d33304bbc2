"""Console scripts kept as they were before the folder split: ``votesplat`` (query_cli),
``votesplat-eval`` and ``votesplat-noisy-masks`` (evaluate_cli), ``votesplat-masks`` (masks_cli),
and the shared one-line error reporting (cli_errors). ``votesplat-export`` lives in ns/export.py and
``votesplat-synth`` in eval/synthetic/cli.py.
"""
