"""The ``dm2`` command line (typer + rich). Only the CLI wires dm2, calib and twin together."""
