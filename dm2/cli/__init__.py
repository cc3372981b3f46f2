"""The ``dm2`` command line (typer + rich). Only the CLI wires dm2, calib and twin together.

Importing the CLI imports ``twin.schema``, which types the twin's scenario sections for every
scenario any command reads (``dm2.core.config.register_scenario_model``).
"""

import twin.schema  # noqa: F401
