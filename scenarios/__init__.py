"""Shipped scenarios (TOML) and the part-geometry generators they name."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

DEFAULT_SCENARIO = "seven_sided_corner_overbuild"


def scenario_dir() -> Path:
    """Folder holding the shipped scenario TOML files."""
    return Path(str(resources.files(__name__)))


def list_scenarios() -> list[str]:
    return sorted(p.stem for p in scenario_dir().glob("*.toml"))


def resolve_scenario(name_or_path: str | None) -> Path:
    """A path to a scenario file: an existing path, or the name of a shipped scenario."""
    if name_or_path is None:
        name_or_path = DEFAULT_SCENARIO
    p = Path(name_or_path)
    if p.exists():
        return p
    shipped = scenario_dir() / f"{p.stem if p.suffix == '.toml' else name_or_path}.toml"
    if shipped.exists():
        return shipped
    raise FileNotFoundError(
        f"scenario '{name_or_path}' is neither a file nor a shipped scenario "
        f"(shipped: {', '.join(list_scenarios())})")
