"""Run one scenario in process: the twin, the monitoring session and the report, in one call.

:func:`run_scenario` is the body of ``dm2 run`` and of every bench and sweep case: it builds
the twin's :class:`twin.stream.simulate.Simulation`, streams its messages into a
:class:`dm2.pipeline.pipeline.Pipeline` (optionally recording them to MCAP), writes the report
with the twin's fault truth and the scenario's ``[expect]`` section, and measures how far each
layer's reconstructed surface lies from the twin's true surface of the same layer.

This module wires the twin and the pipeline together, so it lives beside the CLI and imports
the twin lazily.
"""

from __future__ import annotations

import json
import logging
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dm2.cli.closed_loop import ClosedLoop
from dm2.core.config import Scenario

log = logging.getLogger(__name__)

Progress = Callable[[float, float], None]  # (process seconds done, total process seconds)
SWEEP_DECIMALS = 6  # sweep results: 1 nm on lengths, far below any scored difference


@dataclass
class ScenarioRun:
    """What :func:`run_scenario` produced.

    Attributes
    ----------
    scenario : the scenario as run (``duration_s`` applied)
    run_dir : the run folder (report.json, truth/, optionally run.mcap and the full report)
    report : the report.json content
    fault_truth : the twin's faults.json content (``{"faults": [...]}``)
    reconstruction : per layer ``{"rms_mm", "p95_mm", "n_vertices"}``: unsigned distance [mm]
        from the observed reconstructed vertices to the twin's true surface of that layer
    footprints : track id -> {layer: (xy_O (k, 2) [mm], area (k,) [mm^2])}, the vertices of
        each track's regions (what the strict scoring tests against the truth maps)
    track_truth : track id -> its flagged vertices against the reference and the twin's true
        surface (:func:`dm2.bench.reconstruction.truth_checks`; report.json ``track_truth``)
    process_s : float [s], simulated process time
    wall_s : float [s], wall time of the whole run (twin included)
    monitor_s : float [s], wall time spent in the pipeline (fusion, reference, analysis)
    verdict : ``(code, sentence)`` of :func:`dm2.cli.outcome.run_verdict`, as ``dm2 monitor``
        judges a run: exit 1 and why when it fused nothing or lost too much of its input
    truth_validity : the twin's check of its own truth (truth/validity.json; report.json
        ``truth_validity``), or None where the twin wrote none
    """

    scenario: Scenario
    run_dir: Path
    report: dict
    fault_truth: dict
    reconstruction: dict[int, dict] = field(default_factory=dict)
    footprints: dict = field(default_factory=dict)
    track_truth: dict = field(default_factory=dict)
    process_s: float = 0.0
    wall_s: float = 0.0
    monitor_s: float = 0.0
    verdict: tuple[int, str | None] = (0, None)
    truth_validity: dict | None = None


def recorded(messages, writer):
    """``messages``, each also written to ``writer`` (a RecordingWriter) on the way."""
    for msg in messages:
        writer.write(msg)
        yield msg


def stream_to_pipeline(sim, pipeline, scratch: Path, record: bool,
                       progress: Progress | None = None, tap=None, next_layer=None) -> None:
    """Run ``pipeline`` on the simulation's message stream (truth into ``scratch/truth``).

    With ``record`` the stream is also written to ``scratch/run.mcap`` with the scenario,
    toolpath and calibration attached; ``tap`` (a dm2.report.scene_inputs.StreamTap) sees
    every message on the way. ``next_layer``: the closed loop's hook
    (:meth:`twin.stream.simulate.Simulation.messages`).
    """
    messages = sim.messages(truth_dir=scratch / "truth", progress=progress,
                            next_layer=next_layer)
    if tap is not None:
        messages = tap.wrap(messages)
    if not record:
        pipeline.run(messages)
        return
    from dm2.io.recording_writer import RecordingWriter

    writer = RecordingWriter(scratch / "run.mcap", attachments=sim.attachments())
    writer.write_static_tf(sim.calibration)
    try:
        pipeline.run(recorded(messages, writer))
    finally:
        writer.close()


def run_scenario(sc: Scenario, run_dir: str | Path, *, scenario_file: str | Path | None = None,
                 record: bool = False, full_report: bool = True,
                 progress: Progress | None = None,
                 on_stream_end: Callable[[], None] | None = None,
                 calibration=None, force: bool = False, on_layer: Callable | None = None,
                 report_stage: Callable[[str, int, int], None] | None = None,
                 on_pipeline: Callable | None = None,
                 include: dict | None = None,
                 true_T_B_S: dict | None = None, scene: bool = False,
                 compensate: str = "off") -> ScenarioRun:
    """Simulate ``sc`` on the twin, monitor it and write the run folder ``run_dir``.

    Parameters
    ----------
    sc : the scenario (apply ``duration_s`` before calling)
    run_dir : the run folder, written only once the run has finished; an earlier dm2 run there is
        replaced, a folder holding other files is refused (ValueError) unless ``force``, which
        replaces only dm2's files (:mod:`dm2.report.outdir`)
    scenario_file : where the scenario came from (recorded in report.json)
    record : also keep the raw stream as ``run.mcap``
    full_report : the whole report folder (meshes, maps, plots, HTML); otherwise report.json
        and tracks.csv only (the bench's default: the pictures cost more than the monitor)
    progress : called with (process seconds done, total) while the twin runs
    on_stream_end : called once the stream is consumed, before the report is written
    calibration : dm2.core.messages.Calibration the pipeline uses instead of the one the scenario
        hands it (e.g. a solved hand-eye calibration against a perturbed ``calibration_error``)
    on_layer : called with each analysed layer's LayerResult (the pipeline's ``on_layer``)
    report_stage : called with (stage, done, total) while the report is written
    on_pipeline : called with the Pipeline once it exists (e.g. to attach a view)
    include : name -> path of further files moved into the run folder (e.g. its log file)
    true_T_B_S : the twin's profilers as built (dict sensor id -> (4, 4)) instead of the
        scenario's nominal layout
    scene : also write ``scene.mcap``, the run in Foxglove's schemas
        (:mod:`dm2.report.scene_mcap`)
    compensate : "off"; "advise": each next layer corrected from the monitor's measured top
        (``[control]``, :mod:`dm2.control`) and written to ``corrections/`` as a RAPID module
        and a CSV; "apply": the twin also executes the corrected layers (it pauses
        ``[control] layer_pause_s`` before each layer, the powder off on the way there, for
        the monitor to close the layer before); "hold": those pauses without corrections

    Raises
    ------
    twin.cell.kinematics.ReachError : the toolpath leaves the robot's reach (nothing written)
    ValueError : ``run_dir`` cannot be written (nothing written)
    """
    from dm2.bench.reconstruction import truth_checks
    from dm2.cli.outcome import run_verdict
    from dm2.core.toml_write import dump_toml
    from dm2.pipeline.pipeline import Pipeline
    from dm2.report import check_output_dir
    from twin.stream.simulate import Simulation

    t_start = time.perf_counter()
    run_dir = check_output_dir(run_dir, force=force)
    sim = Simulation(sc, true_T_B_S=true_T_B_S,
                     layer_pause_s=sc.control.layer_pause_s if compensate in ("apply", "hold")
                     else 0.0)
    loop = ClosedLoop(sim, sc, compensate, on_layer)
    pipeline = Pipeline(calibration or sim.calibration, sc.monitor, sc.process,
                        plate_size_mm=sc.cell.plate_size_mm, toolpath=sim.toolpath,
                        on_layer=loop.on_layer)
    if on_pipeline is not None:
        on_pipeline(pipeline)
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=".dm2-run-", dir=run_dir.parent))
    try:
        tap = None
        if scene:
            from dm2.report.scene_inputs import StreamTap

            tap = StreamTap()
        loop.out_dir(scratch / "corrections")
        stream_to_pipeline(sim, pipeline, scratch, record, progress, tap=tap,
                           next_layer=loop.next_layer)
        if on_stream_end is not None:
            on_stream_end()
        truth = _read_json(scratch / "truth" / "faults.json") or {"faults": []}
        validity = _read_json(scratch / "truth" / "validity.json")
        recon, tracks_vs_truth = truth_checks(pipeline.results, scratch / "truth",
                                              tolerance_mm=sc.monitor.delta_global_mm)
        footprints = track_footprints(pipeline.results)
        timing = pipeline.timing()
        monitor_s = timing["fusion_s"] + timing["reference_s"] + timing["analysis_s"]
        timing.update(simulated_process_s=sim.end_s, monitor_s=monitor_s,
                      wall_s=time.perf_counter() - t_start)
        meta = {"scenario": sc.name, "scenario_file": str(scenario_file or ""), "seed": sc.seed,
                "layers_simulated": len(pipeline.results)}
        include = {**{name: scratch / name for name in ("truth", "run.mcap", "corrections")
                      if (scratch / name).exists()}, **(include or {})}
        report = pipeline.write_outputs(
            run_dir, full=full_report, config_toml=dump_toml(sc.to_toml_dict()),
            timing=timing, fault_truth=truth, expect=sc.expect, meta=meta,
            sections=pipeline.sections(
                reconstruction={str(k): v for k, v in recon.items()},
                track_truth={str(k): v for k, v in tracks_vs_truth.items()},
                truth_validity=validity, **loop.sections()),
            force=force, include=include, command="dm2 run" if full_report else "dm2 bench",
            inputs=[scenario_file], stage=report_stage)
        if scene:
            from dm2.report.scene_mcap import add_scene_to_run, scene_items

            add_scene_to_run(run_dir, scene_items(pipeline.results, report,
                                                  pipeline.fusion.calibration, tap))
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    verdict = run_verdict(profiles_fused=pipeline.fusion.profiles_fused,
                          dropped=pipeline.dropped, messages_in=pipeline.messages,
                          max_lost_share=sc.monitor.gates.max_lost_share)
    return ScenarioRun(scenario=sc, run_dir=run_dir, report=report, fault_truth=truth,
                       reconstruction=recon, footprints=footprints,
                       track_truth=tracks_vs_truth, process_s=float(sim.end_s),
                       wall_s=time.perf_counter() - t_start, monitor_s=float(monitor_s),
                       verdict=verdict, truth_validity=validity)


def track_footprints(results) -> dict:
    """Each track's vertices per layer: {track id: {layer: (xy_O (k, 2), area (k,))}}."""
    out: dict = {}
    for r in results:
        if not r.regions:
            continue
        areas = r.deviation.vertex_areas()
        xy = r.deviation.vertices_O[:, :2]
        for reg, tid in zip(r.regions, r.track_ids, strict=True):
            if tid is None:
                continue
            ids = np.asarray(reg.vertex_ids)
            layers = out.setdefault(int(tid), {})
            prev = layers.get(int(r.layer))
            new = (xy[ids], areas[ids])
            layers[int(r.layer)] = new if prev is None else (
                np.vstack([prev[0], new[0]]), np.concatenate([prev[1], new[1]]))
    return out


def _read_json(path: Path):
    return json.loads(path.read_text(encoding="utf-8")) if path.exists() else None


def score_scenario_run(run: ScenarioRun) -> dict:
    """:func:`dm2.bench.scoring.score_run` of a finished run, with its scenario's settings."""
    from dm2.bench.scoring import score_run
    from dm2.bench.truth_maps import load_truth_maps
    from twin.world.coupon import coupon_scale

    # the scale the twin deposits at: its [twin_process] factors times what its efficiency
    # curve takes at normal spray on a flat raster coupon
    return score_run(run.report, run.fault_truth,
                     truth_maps=load_truth_maps(run.run_dir / "truth"),
                     footprints=run.footprints, reconstruction=run.reconstruction,
                     track_truth=run.track_truth, process_s=run.process_s,
                     monitor_s=run.monitor_s, wall_s=run.wall_s,
                     expected_process_scale=coupon_scale(run.scenario),
                     truth_validity=run.truth_validity,
                     event_tolerance_mm=run.scenario.monitor.delta_global_mm)


def sweep_case(scenario_dict: dict, source: str) -> dict:
    """One Monte Carlo case (run in a sweep worker): the scored run without timings.

    ``scenario_dict`` is a complete scenario (seed and fault size already set); the run folder
    is temporary. The result depends only on the scenario, so equal seeds give equal results:
    floats are rounded to :data:`SWEEP_DECIMALS` decimals, below which the summation order of
    vectorised and threaded kernels (memory alignment, thread count) may differ between runs.
    """
    from dm2.core.config import parse_scenario

    sc = parse_scenario(scenario_dict, source)
    with tempfile.TemporaryDirectory(prefix="dm2-sweep-") as tmp:
        run = run_scenario(sc, Path(tmp) / "run", full_report=False)
        score = score_scenario_run(run)
    fault = score["faults"][0] if score["faults"] else {}
    keep = ("detected", "detected_global", "sign_ok", "qualifies", "peak_height_mm", "onset_layer",
            "first_layer_detected", "onset_delay_layers", "iou", "height_error_mm")
    return _rounded({**{k: fault.get(k) for k in keep},
                     "false_positive_tracks": len(score["false_tracks"]),
                     "drift_tracks": len(score.get("drift_tracks", [])),
                     "realtime_false_alarms": score["realtime_false_alarms"],
                     "layers": score["layers"],
                     "reconstruction_rms_mm": score["reconstruction_rms_mm"]})


def _rounded(obj, decimals: int | None = None):
    decimals = SWEEP_DECIMALS if decimals is None else decimals
    if isinstance(obj, dict):
        return {k: _rounded(v, decimals) for k, v in obj.items()}
    if isinstance(obj, float):
        return round(obj, decimals)
    return obj
