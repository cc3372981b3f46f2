"""Entry point of the ``dm2`` console command: imports every command module, then runs."""

from dm2.cli.common import app

# Each command module registers itself on ``app`` when imported (one line per module).
COMMAND_MODULES = [
    "cmd_simulate",
    "cmd_toolpath",
    "cmd_monitor",
    "cmd_calibrate",
    "cmd_fit",
    "cmd_run",
    "cmd_live",
    "cmd_bench",
    "cmd_sweep",
    "cmd_view",
]

for _name in COMMAND_MODULES:
    __import__(f"dm2.cli.{_name}")

__all__ = ["app"]

if __name__ == "__main__":
    app()
