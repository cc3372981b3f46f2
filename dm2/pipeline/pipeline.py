"""The pipeline of the method: messages in, per-layer results and the run folder out.

:class:`Pipeline` is the one object every driver builds (``dm2 run``, ``dm2 bench``,
``dm2 monitor`` and live mode). :meth:`Pipeline.run` takes any iterable of messages (the twin's
stream, a recording reader, a live inbox) through the stages of the paper's sections 5 and 6 in
this order (:data:`STAGES`, :meth:`Pipeline.stages` names the object doing each):

1. sync: pair each profile with the robot poses around it (:class:`~dm2.fusion.sync.StreamSync`,
   behind the optional input gates);
2. register: profile points into the work object frame ``O`` (``T_O_S`` of its pose);
3. fuse: into the sparse TSDF (:class:`~dm2.fusion.fusion.TsdfFusion`);
4. surface: the layer's mesh when a layer closes (:class:`~dm2.fusion.surface.SurfaceExtractor`);
5. reference: the near-net reference grown along the executed motion
   (:class:`~dm2.reference.model.NearNetReference`, fed by
   :class:`~dm2.reference.feed.ReferenceFeed`);
6. deviation, 7. classify, 8. segment, 9. track: the layer's analysis against the reference of
   the same layer (:class:`~dm2.defects.layer_analysis.LayerAnalysis`).

The stages run interleaved in stream order inside :class:`~dm2.pipeline.session.MonitoringSession`
(its typed events in dm2.pipeline.events order the reference steps). A live source
feeds messages one at a time instead: :meth:`Pipeline.feed` (with ``live=True`` it fuses only),
:meth:`Pipeline.catch_up` in the idle moments, :meth:`Pipeline.finish` at the end;
:meth:`Pipeline.run` is the loop over :meth:`feed` for finite sources. :meth:`write_outputs`
writes the run folder (report.json, tracks.csv, meshes, maps, index.html) and
:meth:`write_layer_surface` one finished layer's fused surface.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path

from dm2.core.config import MonitorConfig, ProcessConfig
from dm2.core.messages import Calibration, Toolpath
from dm2.defects.layer_analysis import LayerResult
from dm2.pipeline.session import MonitoringSession

STAGES = ("sync", "register", "fuse", "surface", "reference", "deviation", "classify", "segment",
          "track")


class Pipeline:
    """The monitoring method for one build.

    Parameters
    ----------
    calibration : the calibration the pipeline trusts (``T_B_S``, ``T_F_O``, ``T_B_N``)
    monitor_cfg : fusion and deviation settings
    process : nominal process parameters (near-net reference, active region)
    plate_size_mm : (Lx, Ly[, thickness]) [mm], extent of the reference height map
    toolpath : optional; splits layers when the stream carries no layer marks
    on_layer : optional callback ``f(LayerResult)`` when a layer has been analysed
    live : fusion first: :meth:`feed` only fuses, the reference update and the real-time
        comparison wait for :meth:`catch_up`, layers are analysed on a worker thread; the same
        layer results and tracks as a replay
    gates : optional :class:`~dm2.fusion.gates.InputGates` every message passes first
    """

    def __init__(self, calibration: Calibration, monitor_cfg: MonitorConfig,
                 process: ProcessConfig, plate_size_mm=(120.0, 120.0),
                 toolpath: Toolpath | None = None,
                 on_layer: Callable[[LayerResult], None] | None = None,
                 live: bool = False, gates=None):
        self.cfg = monitor_cfg
        self.process = process
        self.toolpath = toolpath
        self.live = bool(live)
        self.session = MonitoringSession(calibration, monitor_cfg, process,
                                         plate_size_mm=tuple(plate_size_mm[:2]),
                                         toolpath=toolpath, on_layer=on_layer,
                                         analysis_thread=self.live, gates=gates)
        self.messages = 0  # messages taken from the source (before the gates)

    # ------------------------------------------------------------------------------ the method
    def stages(self) -> dict:
        """The object doing each stage of :data:`STAGES`, in order."""
        s = self.session
        return {"sync": s.fusion.sync, "register": s.fusion, "fuse": s.fusion.tsdf,
                "surface": s.fusion.extractor, "reference": s.reference,
                "deviation": s.defects, "classify": s.defects, "segment": s.defects,
                "track": s.defects.tracker}

    def run(self, source: Iterable) -> list[LayerResult]:
        """Every message of ``source`` through sync, register, fuse, surface, reference,
        deviation, classify, segment and track (:data:`STAGES`); the analysed layers."""
        for msg in source:
            self.feed(msg)
        return self.finish()

    def feed(self, msg) -> None:
        """One message (Profile, RobotState or LayerMark); bad ones are counted, never raised.
        With ``live`` only the fusion runs now (see :meth:`catch_up`)."""
        self.messages += 1
        self.session.feed(msg, defer=self.live)

    def catch_up(self, should_yield: Callable[[], bool] | None = None) -> bool:
        """The reference updates, real-time comparison and pre-meshing :meth:`feed` left
        (``live``); True when nothing is left (see MonitoringSession.catch_up)."""
        return self.session.catch_up(should_yield)

    @property
    def behind(self) -> bool:
        """True while deferred work waits for :meth:`catch_up`."""
        return self.session.behind

    def finish(self) -> list[LayerResult]:
        """End of stream: close the last layer, analyse it and end the tracks."""
        return self.session.finish()

    # ------------------------------------------------------------------------------- state
    @property
    def fusion(self):
        """The :class:`~dm2.fusion.fusion.TsdfFusion` stage (sync, register, fuse, surface)."""
        return self.session.fusion

    @property
    def results(self) -> list[LayerResult]:
        return self.session.results

    @property
    def tracks(self):
        return self.session.tracks

    @property
    def dropped(self) -> dict[str, int]:
        return self.session.dropped

    @property
    def last_T_B_F(self):
        """The newest robot flange pose (4, 4) in ``B`` integrated so far, or None."""
        return self.session.states.last_T_B_F

    def timing(self, **extra) -> dict:
        """Wall seconds per stage and the message count, plus ``extra`` entries."""
        return {**self.session.timing.to_dict(), **extra}

    def sections(self, **extra) -> dict:
        """The report sections of the pipeline (real-time alarms, process fit, the points
        rejected before fusion: dm2.fusion.point_filter) plus ``extra``."""
        pf = self.session.fusion.point_filter
        return {"realtime": self.session.realtime_summary(),
                "process": self.session.process_summary(),
                **({"point_filter": pf.summary()} if pf is not None else {}), **extra}

    # ----------------------------------------------------------------------------- outputs
    def write_outputs(self, out_dir: str | Path, *, full: bool = True, results=None,
                      tracks=None, dropped: dict | None = None, sections: dict | None = None,
                      include: dict | None = None, command: str = "",
                      config_toml: str | None = None, **report_args) -> dict:
        """Write the run folder ``out_dir`` and return the report.json content.

        ``full``: report.json, tracks.csv, per-layer deviation meshes and maps, plots and
        index.html (:func:`dm2.report.write_report`; ``report_args`` are the folder's
        ``inputs``, ``force`` and ``stage`` and fields of its
        :class:`~dm2.report.report_content.ReportContent`: timing, meta, fault_truth, expect,
        map_layers, limit_mm, toolpath, which defaults to the pipeline's);
        otherwise config.toml, report.json and tracks.csv only. ``results``/``tracks``
        default to the pipeline's own (a snapshot of them for interim reports), ``dropped``
        to :attr:`dropped`, ``sections`` to :meth:`sections`; ``include`` moves further files
        (name -> path) into the folder.
        """
        from dm2.report import ReportContent, write_report
        from dm2.report.report_json import build_report

        results = self.results if results is None else results
        tracks = self.tracks if tracks is None else tracks
        dropped = self.dropped if dropped is None else dropped
        sections = self.sections() if sections is None else sections
        out_dir = Path(out_dir)
        folder = {name: report_args.pop(name) for name in ("inputs", "force", "stage")
                  if name in report_args}
        content = ReportContent(config_toml=config_toml, dropped=dropped, sections=sections,
                                **{"toolpath": self.toolpath, **report_args})
        if full:
            return write_report(out_dir, results, tracks, content, include=include,
                                command=command, **folder)
        report = build_report(results, tracks, dropped=dropped, sections=sections,
                              timing=content.timing, meta=content.meta,
                              fault_truth=content.fault_truth, expect=content.expect)
        _write_lite_report(out_dir, report, tracks, config_toml or "", include or {},
                           command)
        return report

    def write_layer_surface(self, out_dir: str | Path, index: int = -1) -> dict:
        """Write the ``index``-th finished layer's fused surface to
        ``out_dir/layer_NNNN.ply`` (frame O, mm, per-vertex ``scalar_weight``); its entry for
        a summary (layer, file, stamp, vertex and face counts, area)."""
        ls = self.fusion.layer_done[index]
        path = Path(out_dir) / f"layer_{ls.layer:04d}.ply"
        ls.surface.write_ply(path)
        return {"layer": ls.layer, "file": path.name, "stamp_s": ls.stamp_s,
                "vertices": ls.surface.n_vertices, "faces": ls.surface.n_faces,
                "area_mm2": round(ls.surface.area_mm2(), 3)}


def _write_lite_report(run_dir: Path, report: dict, tracks, config_toml: str, include: dict,
                       command: str) -> None:
    """config.toml, report.json and tracks.csv (and ``include``), installed as one folder."""
    from dm2.report.outdir import files_below, install_folder, write_manifest
    from dm2.report.report_json import write_tracks_csv

    tmp = Path(tempfile.mkdtemp(prefix=f".{run_dir.name}.", dir=run_dir.parent))
    try:
        (tmp / "config.toml").write_text(config_toml, encoding="utf-8")
        (tmp / "report.json").write_text(json.dumps(report, indent=1), encoding="utf-8")
        write_tracks_csv(tmp / "tracks.csv", tracks)
        for name, path in include.items():
            shutil.move(str(path), str(tmp / name))
        write_manifest(tmp, files_below(tmp), command=command)
        install_folder(tmp, run_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
