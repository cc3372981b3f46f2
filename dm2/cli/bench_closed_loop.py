"""``dm2 bench --compensate``: each scenario open and closed loop from the same seed, every
layer's true top scored against the design intent (:mod:`dm2.bench.intent`).

Open loop is the closed loop's cell program without corrections (``compensate="hold"``: the
same pauses between layers, the powder off on the way), so the two differ only by the speeds.
"""

from __future__ import annotations

from pathlib import Path

from dm2.bench.intent import score_top

KEYS = ("out_of_tolerance_mm2", "out_of_tolerance_mm3", "max_abs_deviation_mm", "top_error_mm")
RECOVERED_SHARE = 0.05  # a layer is out of tolerance above this share of the footprint


def score_layers(run, tolerance_mm: float) -> list[dict]:
    """Each truth layer of a finished run (``truth/layer_NNN.ply``) against the intent."""
    import trimesh

    from dm2.toolpath import generate_toolpath
    from scenarios.parts import build_part

    sc = run.scenario
    tp = generate_toolpath(build_part(sc.part, sc.cell.plate_size_mm), sc.toolpath)
    out = []
    for ply in sorted((Path(run.run_dir) / "truth").glob("layer_*.ply")):
        mesh = trimesh.load(ply, process=False)
        out.append(score_top(mesh.vertices, tp, int(ply.stem.split("_")[1]),
                             sc.toolpath.layer_mm, sc.toolpath.line_spacing_mm, tolerance_mm))
    return out


def layers_to_recover(layers: list[dict]) -> int | None:
    """Layers from the first one out of tolerance to the first one back within it (0: never
    out; None: not back by the last layer)."""
    bad = [r["out_of_tolerance_mm2"] > RECOVERED_SHARE * r["footprint_mm2"] for r in layers]
    if not any(bad):
        return 0
    first = bad.index(True)
    for k in range(first + 1, len(bad)):
        if not bad[k]:
            return k - first
    return None


def closed_loop_case(sc, out_dir: Path, scenario_file, full: bool, tolerance_mm: float) -> dict:
    """Both arms of one scenario, written to ``out_dir/open`` and ``out_dir/closed``."""
    from dm2.cli.bench_runner import run_scenario

    case = {}
    for arm, mode in (("open", "hold"), ("closed", "apply")):
        run = run_scenario(sc, out_dir / arm, scenario_file=scenario_file, full_report=full,
                           compensate=mode, record=False)
        layers = score_layers(run, tolerance_mm)
        control = run.report.get("sections", {}).get("control") or run.report.get("control")
        case[arm] = {"final": layers[-1] if layers else None, "layers": layers,
                     "layers_to_recover": layers_to_recover(layers),
                     "late_layers": (control or {}).get("late_layers", [])}
    return case


def closed_loop_lines(name: str, case: dict) -> list[str]:
    """The printed comparison of one scenario's final layer."""
    o, c = case["open"]["final"], case["closed"]["final"]
    if o is None or c is None:
        return [f"{name}: no layer scored"]
    lines = [f"{name} (layer {o['layer']}, footprint {o['footprint_mm2']:.0f} mm²)"]
    for k in KEYS:
        lines.append(f"  {k:<24} open {o[k]:>9.3f}   closed {c[k]:>9.3f}")
    lines.append(f"  {'layers_to_recover':<24} open {case['open']['layers_to_recover']!s:>9}"
                 f"   closed {case['closed']['layers_to_recover']!s:>9}")
    return lines
