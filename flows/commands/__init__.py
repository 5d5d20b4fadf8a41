"""The `mobileocc` subcommands that are not the pipeline: simulate, show, evaluate (and its report),
check-data."""
