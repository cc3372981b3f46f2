"""The house rules of ARCHITECTURE.md, checked: import contracts, module size, folder size."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GENERATED = {"dm2/live/egm_pb2.py"}  # protoc output, not written by hand
MAX_MODULE_LINES = 400


def test_import_contracts_hold():
    """``lint-imports``: the layers, no twin in dm2/calib, no cycles (pyproject.toml)."""
    exe = Path(sys.executable).with_name("lint-imports")
    assert exe.exists(), "import-linter is a dev dependency: pip install -e '.[dev]'"
    done = subprocess.run([str(exe), "--no-cache"], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.count(" KEPT") == 5 and "BROKEN" not in done.stdout


def test_no_module_over_the_size_limit():
    too_long = {}
    for package in ("dm2", "twin", "calib", "scenarios"):
        for path in (ROOT / package).rglob("*.py"):
            rel = path.relative_to(ROOT).as_posix()
            n = len(path.read_text().splitlines())
            if rel not in GENERATED and n > MAX_MODULE_LINES:
                too_long[rel] = n
    assert too_long == {}


@pytest.mark.parametrize("package,limit", [("dm2", 10), ("twin", 8)])
def test_top_level_holds_folders_not_modules(package, limit):
    modules = sorted(p.name for p in (ROOT / package).glob("*.py"))
    assert len(modules) <= limit, modules
