"""The documentation's runnable examples and the examples/ scripts run, and say what they should.

A fenced block in ``docs/*.md`` directly under a ``<!-- runnable -->`` line is run here: shell
blocks with ``dm2`` on the PATH (this interpreter's ``python -m dm2.cli.main``), Python blocks
with this interpreter, each in a fresh folder that holds the repository's ``scenarios/`` and
``examples/``; it must exit 0. The three scripts in
``examples/`` are run on known inputs and their output checked against the known truth.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RUNNABLE = re.compile(r"<!-- runnable -->\n```(bash|python)\n(.*?)\n```", re.S)


def runnable_blocks() -> list[tuple[str, str, str]]:
    blocks = []
    for page in sorted((ROOT / "docs").glob("*.md")):
        text = page.read_text(encoding="utf-8")
        for i, match in enumerate(RUNNABLE.finditer(text)):
            blocks.append((f"{page.name}#{i}", match.group(1), match.group(2)))
    return blocks


def shell_env(tmp_path: Path) -> dict:
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    shim = bin_dir / "dm2"
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m dm2.cli.main "$@"\n')
    shim.chmod(0o755)
    return {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
            "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}


def test_the_docs_have_runnable_examples():
    assert len(runnable_blocks()) >= 2


@pytest.mark.parametrize("name,lang,code", runnable_blocks(), ids=lambda v: str(v)[:40])
def test_runnable_doc_example(tmp_path, name, lang, code):
    work = tmp_path / "work"  # stands for the repository root, where the docs' examples run
    work.mkdir()
    for shipped in ("scenarios", "examples"):
        (work / shipped).symlink_to(ROOT / shipped, target_is_directory=True)
    cmd = ["bash", "-euo", "pipefail", "-c", code] if lang == "bash" else [sys.executable, "-c",
                                                                           code]
    proc = subprocess.run(cmd, cwd=work, env=shell_env(tmp_path), capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, f"{name}: exit {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    assert "Traceback" not in proc.stderr


def run_example(tmp_path: Path, script: str, *args: str) -> str:
    proc = subprocess.run([sys.executable, str(ROOT / "examples" / script), *args],
                          cwd=tmp_path, env=shell_env(tmp_path), capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_example_compare_mesh_finds_the_raised_half(tmp_path):
    out = run_example(tmp_path, "compare_mesh.py")
    # the right half stands 0.5 mm over the reference, the left half on it
    assert "deviation +0.00 to +0.50 mm" in out
    assert "x 60.0 to 68.9 mm" in out


@pytest.mark.slow
def test_example_run_scenario_finds_the_bump_and_nothing_else(tmp_path):
    out = run_example(tmp_path, "run_scenario.py")
    tracks = [line for line in out.splitlines() if line.startswith("track ")]
    # the smoke bump: 1.2 mm high, 4 mm wide, at (60, 60) mm, landing at the end of layer 1
    assert len(tracks) == 1, out
    m = re.match(r"track \d+: overbuild from layer ([12]) at \(([\d.]+), ([\d.]+)\) mm, "
                 r"[\d.]+ mm², \+([\d.]+) mm", tracks[0])
    assert m, tracks[0]
    assert abs(float(m[2]) - 60.0) < 2.0 and abs(float(m[3]) - 60.0) < 2.0
    assert 0.8 < float(m[4]) < 1.8


@pytest.mark.slow
def test_example_monitor_recording_reports_the_bump(tmp_path):
    sim = subprocess.run([sys.executable, "-m", "dm2.cli.main", "simulate",
                          str(ROOT / "scenarios/suites/smoke/bump.toml"), "--out", "run.mcap"],
                         cwd=tmp_path, env=shell_env(tmp_path), capture_output=True, text=True,
                         timeout=600)
    assert sim.returncode == 0, sim.stderr
    out = run_example(tmp_path, "monitor_recording.py", "run.mcap", "out")
    assert "3 layers, 1 track(s)" in out
    assert re.search(r"track \d+: overbuild from layer [12]$", out, re.M), out
    assert (tmp_path / "out" / "index.html").is_file()
