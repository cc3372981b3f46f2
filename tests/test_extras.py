"""An installation without the optional extras monitors recordings; a command that needs an
extra says which one to install (exit 2, no traceback).

The extras' packages are hidden from a child interpreter (``sys.modules[name] = None`` makes
their import fail as if they were not installed), which then runs the real command.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BUMP = ROOT / "scenarios" / "suites" / "smoke" / "bump.toml"
EXTRAS = {"twin": "pybullet", "view": "viser", "cluster": "distributed"}
RUN = ("import sys\n"
       "for name in sys.argv[1].split(','):\n"
       "    sys.modules[name] = None\n"
       "from dm2.cli.main import app\n"
       "app(args=sys.argv[2:], prog_name='dm2')\n")


def dm2_without(hidden: list[str], *args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", RUN, ",".join(hidden), *map(str, args)],
                          cwd=cwd, capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_without_extras_a_recording_is_monitored(tmp_path):
    hidden = [*EXTRAS.values(), "dask"]
    sim = dm2_without(hidden, "simulate", BUMP, "--out", "run.mcap", cwd=tmp_path)
    assert sim.returncode == 0, sim.stderr
    mon = dm2_without(hidden, "monitor", "run.mcap", "--out", "out", cwd=tmp_path)
    assert mon.returncode == 0, mon.stderr
    report = json.loads((tmp_path / "out" / "report" / "report.json").read_text())
    tracks = report["tracks"]
    # the smoke bump (1.2 mm at (60, 60) mm from layer 1) and nothing else
    assert [t["kind"] for t in tracks] == ["overbuild"], tracks
    assert tracks[0]["first_layer"] in (1, 2)


@pytest.mark.parametrize("extra,args", [
    ("view", ["view", "."]),
    ("cluster", ["sweep", str(BUMP), "--sizes", "0.5", "--seeds", "1"]),
    ("twin", ["simulate", str(BUMP), "--out", "run.mcap", "--gui"]),
])
def test_a_command_names_the_extra_it_needs(tmp_path, extra, args):
    proc = dm2_without([EXTRAS[extra]], *args, cwd=tmp_path)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert f"pip install 'dm2[{extra}]'" in proc.stderr.replace("\n", "")
    assert EXTRAS[extra] in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "run.mcap").exists()
