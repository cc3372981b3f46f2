"""The twin played as the cell over loopback sockets (hardware-in-the-loop rehearsal).

:func:`serve_twin` runs a scenario's simulation and sends its stream the way the real cell
does: robot states as ABB EGM ``EgmRobot`` datagrams over UDP in the RobotWare 7 layout (the
layer index in ``RAPIDfromRobot.dnum[0]``, as the RAPID program of the README reports it through
``EGMActPose \\DataToSensor``), profiles as frames of the
TCP profile protocol (:mod:`dm2.live.tcp_frames`) through a bridge connection that
reconnects if dropped. Messages leave at their stamps, in real time (``speed=1``) or
accelerated; ``speed <= 0`` sends as fast as the twin produces them.
:func:`write_cell_files` writes the cell file (calibration, toolpath, addresses) a live
monitor needs to follow the served twin.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from dm2.core.messages import LayerMark, Profile, RobotState
from dm2.core.toml_write import dump_toml
from twin.schema import TwinScenario

log = logging.getLogger(__name__)

UNPACED_CLOCK_TOLERANCE_S = 30.0  # [s] clock band of a cell file for a twin served unpaced
UNPACED_REORDER_WINDOW_S = 30.0  # [s] reorder window of a cell file for a twin served unpaced
UNPACED_STAMP_RATE = 1e4  # stream s per host s across a pause of an unpaced twin


@dataclass(frozen=True)
class ServeResult:
    """What :func:`serve_twin` sent: counts by kind, process seconds and bridge reconnects."""

    counts: dict
    process_s: float
    reconnects: int


def write_cell_files(simulation, folder: str | Path, egm: str = "127.0.0.1:6510",
                     profiles: str = "127.0.0.1:6511", live: dict | None = None,
                     speed: float = 1.0) -> Path:
    """Write ``cell.toml``, ``calibration.toml`` and ``toolpath.csv`` for a live monitor of
    ``simulation`` (a :class:`twin.stream.simulate.Simulation`) served at ``speed``; returns the
    cell
    file's path.

    The monitor judges arrival jitter in stream seconds: the clock tolerance band
    (``live.clock_tolerance_s``) and the reorder window (``monitor.reorder_window_s``). Served
    at ``speed`` times real time, a millisecond of jitter on the host is ``speed`` ms of stream
    time, so above real time both are written ``speed`` times as wide (the default band, the
    scenario's window): the same wall-clock margins as on the real cell. Unpaced (speed 0 or
    below) arrival times say nothing about the clocks, nor about the order in which the two
    sockets' messages arrive (a millisecond's lag of one socket's reader is seconds of stream
    time): the band and the reorder window are then 30 s, so the twin's stamps (one clock for
    poses and profiles) pass as they are and no message is dropped as late. The stamp gate's
    ``monitor.gates.stamp_rate_max`` (stream seconds per host second a stream may advance
    across a pause) is scaled likewise. Entries of ``live`` are written as given."""
    from dm2.core.calibration_io import write_calibration_toml
    from dm2.live.config import LiveConfig
    from dm2.toolpath.formats import write_csv

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    sc = simulation.scenario
    monitor = sc.monitor.model_dump(mode="json", exclude_none=True)
    timing = {}
    if speed > 0:
        widen = max(speed, 1.0)  # never narrower than on the real cell
        timing["clock_tolerance_s"] = LiveConfig().clock_tolerance_s * widen
        monitor["reorder_window_s"] = sc.monitor.reorder_window_s * widen
        rate = sc.monitor.gates.stamp_rate_max * widen
    else:
        timing["clock_tolerance_s"] = UNPACED_CLOCK_TOLERANCE_S
        monitor["reorder_window_s"] = UNPACED_REORDER_WINDOW_S
        rate = UNPACED_STAMP_RATE
    monitor["gates"] = {**monitor.get("gates", {}), "stamp_rate_max": rate}
    write_calibration_toml(simulation.calibration, folder / "calibration.toml")
    write_csv(simulation.toolpath, folder / "toolpath.csv")
    doc = {"schema": 1, "name": f"twin:{sc.name}", "calibration": "calibration.toml",
           "toolpath": "toolpath.csv", "plate_size_mm": list(sc.cell.plate_size_mm),
           "process": sc.process.model_dump(mode="json", exclude_none=True),
           "monitor": monitor,
           "live": {"egm": egm, "profiles": profiles, **timing, **(live or {})}}
    path = folder / "cell.toml"
    path.write_text(dump_toml(doc), encoding="utf-8")
    return path


def serve_twin(scenario: TwinScenario, egm: tuple[str, int], profiles: tuple[str, int],
               speed: float = 1.0, *, simulation=None, stop: threading.Event | None = None,
               connect_timeout_s: float = 10.0) -> ServeResult:
    """Play ``scenario`` to a live monitor listening at ``egm`` (UDP) and ``profiles`` (TCP).

    Parameters
    ----------
    scenario : the scenario (``duration_s`` cuts it short)
    egm, profiles : ``(host, port)`` the monitor listens on
    speed : float, process seconds per wall second (``<= 0``: as fast as possible)
    simulation : an already prepared :class:`twin.stream.simulate.Simulation` of ``scenario``
    stop : set it to end early
    connect_timeout_s : float [s], how long to wait for the monitor's profile server, first
        and after a dropped connection (ConnectionError when it does not accept)

    The bridge connects before the first message leaves, and the clock of the stream starts
    only then: a twin started before its monitor waits for it instead of sending into the void
    (the monitor binds its EGM port before its profile server accepts).
    """
    from dm2.live.egm_source import encode_egm_robot
    from dm2.live.tcp_profiles import ProfileClient
    from twin.stream.simulate import Simulation

    sim = simulation if simulation is not None else Simulation(scenario)
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    bridge = ProfileClient(profiles[0], profiles[1], connect_timeout_s=connect_timeout_s)
    counts = {"RobotState": 0, "Profile": 0, "LayerMark": 0}
    layer = None
    t_wall0 = stamp0 = None
    try:
        bridge.connect()
        for msg in sim.messages():
            if stop is not None and stop.is_set():
                break
            if speed > 0:
                if t_wall0 is None:
                    t_wall0, stamp0 = time.monotonic(), msg.stamp_s
                delay = t_wall0 + (msg.stamp_s - stamp0) / speed - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            if isinstance(msg, LayerMark):
                layer = msg.layer
            elif isinstance(msg, RobotState):
                udp.sendto(encode_egm_robot(msg.seq, round(msg.stamp_s * 1000), msg.joints_rad,
                                            msg.T_B_F, stamp_s=msg.stamp_s, layer=layer), egm)
            elif isinstance(msg, Profile):
                bridge.send(msg)
            counts[type(msg).__name__] += 1
    finally:
        bridge.close()
        udp.close()
    log.info("served %s: %s", scenario.name, counts)
    return ServeResult(counts, float(sim.end_s), bridge.reconnects)
