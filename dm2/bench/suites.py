"""Bench suites by name: which scenario files, what the suite is held to.

The scenario files live outside the pipeline package (the shipped ones under
``scenarios/suites/<folder>/``); callers pass that root, so ``dm2`` never imports the twin's
scenario package. A suite argument may also be a folder of scenario TOML files (no targets).
"""

from __future__ import annotations

import ast
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from dm2.core.config import Scenario, parse_scenario


@dataclass(frozen=True)
class Suite:
    """A named set of scenarios and the suite-level targets (see dm2.bench.suite_score.summarize).

    Attributes
    ----------
    name : suite name
    description : one line
    folder : folder name under the suites root
    targets : f1_min, max_onset_delay_layers, max_false_tracks, max_false_alarms_per_hour
        (checked if present; a fault-free control with any track fails the suite regardless)
    full_report : write the full report folder per scenario (plots, meshes) by default
    paper : also compute the paper's height/mass table and layer figures
    """

    name: str
    description: str
    folder: str
    targets: dict = field(default_factory=dict)
    full_report: bool = False
    paper: bool = False


SUITES = {
    "regression": Suite(
        "regression", "Realistic small parts (box, seven-sided part, reduced tower, two STL "
        "parts), default strategy, every fault kind off-centre / at walls / at corners, five "
        "fault-free controls (CI).",
        "regression",
        targets={"f1_min": 0.95, "max_onset_delay_layers": 1, "max_false_tracks": 0,
                 "max_false_alarms_per_hour": 0}),
    "model_error": Suite(
        "model_error", "The regression suite's controls and wall, edge, corner and hole faults "
        "on a twin whose physics departs from the monitor's model as another cell's would "
        "(another efficiency curve: linear, cos or a logistic in the spray angle; plume 15 % "
        "wider or narrower, efficiency 10 % off), with "
        "other seeds: how the one frozen configuration holds off nominal.",
        "model_error",
        targets={"f1_min": 0.95, "max_onset_delay_layers": 1, "max_false_tracks": 0,
                 "max_false_alarms_per_hour": 0}),
    "shapes": Suite(
        "shapes", "Part shapes the monitor was not developed on (a round pad, a ring, a T, a "
        "triangle), default strategy: a fault-free control of each and a bump, a dent in a "
        "flat, a dent at an edge and a feed step (CI).",
        "shapes",
        targets={"f1_min": 0.95, "max_onset_delay_layers": 1, "max_false_tracks": 0,
                 "max_false_alarms_per_hour": 0}),
    "dirty": Suite(
        "dirty", "The regression suite's controls (box, seven-sided part, bracket) and faults "
        "at corners, walls, edges and holes, with other seeds, seen by profilers as dirty as a "
        "cold-spray cell's ([noise] preset = \"realistic\"): what the pipeline holds on "
        "real sensors.",
        "dirty",
        targets={"f1_min": 0.95, "max_onset_delay_layers": 1, "max_false_tracks": 0,
                 "max_false_alarms_per_hour": 0}),
    "smoke": Suite(
        "smoke", "The small pads, one per fault kind plus a control, single strategy: fast.",
        "smoke",
        targets={"f1_min": 0.95, "max_onset_delay_layers": 1, "max_false_tracks": 0,
                 "max_false_alarms_per_hour": 0}),
    "paper": Suite(
        "paper", "The paper's four experiments, qualitatively and at reduced size, on the twin.",
        "paper", full_report=True, paper=True),
}


def resolve_suite(name_or_folder: str, suites_root: str | Path) -> tuple[Suite, list[Path]]:
    """The suite and its scenario files (sorted by name).

    Raises
    ------
    FileNotFoundError : neither a known suite nor a folder of ``*.toml`` files
    """
    if name_or_folder in SUITES:
        suite = SUITES[name_or_folder]
        folder = Path(suites_root) / suite.folder
    else:
        folder = Path(name_or_folder)
        if not folder.is_dir():
            raise FileNotFoundError(f"suite '{name_or_folder}' is neither a known suite "
                                    f"({', '.join(SUITES)}) nor a folder of scenario files")
        suite = Suite(folder.name, f"scenario files in {folder}", str(folder))
    files = sorted(folder.glob("*.toml"))
    if not files:
        raise FileNotFoundError(f"suite '{suite.name}': no scenario files in {folder}")
    return suite, files


def parse_override(text: str) -> tuple[list[str], object]:
    """``"toolpath.max_layers=12"`` -> (["toolpath", "max_layers"], 12).

    The value is a Python/TOML-like literal (number, string, list, true/false); anything that
    does not parse as one is taken as a string.
    """
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise ValueError(f"override '{text}': expected SECTION.KEY=VALUE")
    raw = raw.strip()
    lowered = {"true": True, "false": False}
    if raw in lowered:
        value = lowered[raw]
    else:
        try:
            value = ast.literal_eval(raw)
        except (ValueError, SyntaxError):
            value = raw
    return [p for p in key.strip().split(".") if p], value


def apply_overrides(data: dict, overrides: list[str]) -> dict:
    """A copy of a scenario dict with ``SECTION.KEY=VALUE`` overrides applied.

    List items are addressed by index (``faults.0.height_mm=0.8``).
    """
    import copy

    out = copy.deepcopy(data)
    for text in overrides:
        path, value = parse_override(text)
        node = out
        for part in path[:-1]:
            if isinstance(node, list):
                node = node[int(part)]
            else:
                node = node.setdefault(part, {})
        if isinstance(node, list):
            node[int(path[-1])] = value
        else:
            node[path[-1]] = value
    return out


def load_suite_scenario(path: str | Path, overrides: list[str] = ()) -> Scenario:
    """Read a scenario file and apply overrides; errors name the file and field."""
    from dm2.core.config import ConfigError, load_scenario

    path = Path(path)
    if not overrides:
        return load_scenario(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read scenario file: {exc}") from None
    try:
        data = apply_overrides(data, list(overrides))
    except (IndexError, KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: cannot apply overrides {list(overrides)}: {exc}") from None
    sc = parse_scenario(data, f"{path} (with {', '.join(overrides)})")
    if sc.part.stl is not None and not Path(sc.part.stl).is_absolute():  # as load_scenario
        sc = sc.model_copy(update={"part": sc.part.model_copy(
            update={"stl": str((path.parent / sc.part.stl).resolve())})})
    return sc
