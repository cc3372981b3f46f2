"""Live stream attacks over loopback: forged stamps, a counter collision, a second source.

The twin's stream is sent to the real listeners (EGM over UDP, the profile server over TCP) at
5x real time, the attack beside it; the runner's result is compared with the same clean stream
through the same processing path: every real profile still fused, no track that the clean run
lacks, the attack's messages counted by reason.
"""

import dataclasses
import socket
import time

import numpy as np
import pytest

from dm2.cli.outcome import EXIT_MISSED, EXIT_OK, stream_verdicts
from dm2.core.messages import COUNTER_MODULO, LayerMark, Profile, RobotState
from dm2.live.config import load_cell_file
from dm2.live.egm_source import encode_egm_robot
from dm2.live.runner import LiveRunner
from dm2.live.tcp_profiles import ProfileClient

SPEED = 5.0


@pytest.fixture(scope="module")
def twin(tmp_path_factory):
    from dm2.core.config import load_scenario
    from scenarios import resolve_scenario
    from twin.stream.serve import write_cell_files
    from twin.stream.simulate import Simulation

    sc = load_scenario(resolve_scenario("pad")).model_copy(update={"duration_s": 3.0})
    sim = Simulation(sc)
    msgs = list(sim.messages())
    folder = tmp_path_factory.mktemp("attacks")
    cell = load_cell_file(write_cell_files(sim, folder / "cell", speed=SPEED))
    clean = LiveRunner(cell, folder / "clean", record=False)
    for m in msgs:
        clean.process(m, "profiles 127.0.0.1:1", m.stamp_s / SPEED)
    clean.finish()
    return sim, msgs, clean


def serve(sim, msgs, tmp_path, attack):
    """Send ``msgs`` paced at SPEED to a runner's listeners; ``attack(m, bridge, second)`` is
    called before each profile goes out (``second``: a second profile connection)."""
    from twin.stream.serve import write_cell_files

    cell_path = write_cell_files(sim, tmp_path / "cell", egm="127.0.0.1:0",
                                 profiles="127.0.0.1:0", speed=SPEED)
    runner = LiveRunner(load_cell_file(cell_path), tmp_path / "out", record=False)
    try:
        send(msgs, runner.open_sources(), attack, runner.drain)
        runner.run(idle_stop_s=1.0, max_duration_s=30)
    finally:
        runner.close()
    return runner


def send(msgs, addr, attack, after_each=lambda: None):
    """The twin's messages paced at SPEED to the listeners at ``addr``, the attack beside."""
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    bridge, second = ProfileClient(*addr["profiles"]), _Later(addr["profiles"])
    bridge.connect()  # the monitor is listening: its EGM socket is bound too
    layer, t0, s0 = None, time.monotonic(), msgs[0].stamp_s
    try:
        for m in msgs:
            wait = t0 + (m.stamp_s - s0) / SPEED - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            if isinstance(m, LayerMark):
                layer = m.layer
            elif isinstance(m, RobotState):
                udp.sendto(encode_egm_robot(m.seq, round(m.stamp_s * 1000), m.joints_rad,
                                            m.T_B_F, stamp_s=m.stamp_s, layer=layer),
                           addr["egm"])
            elif isinstance(m, Profile):
                attack(m, bridge, second)
                bridge.send(m)
            after_each()
    finally:  # the stream ends: its bridges leave (not idle_connection)
        udp.close()
        bridge.close()
        second.close()


class _Later:
    """A second bridge that connects with its first frame (an open, silent connection would
    be closed as ``idle_connection``)."""

    def __init__(self, address):
        self.address, self.client = address, None

    def send(self, p):
        if self.client is None:
            self.client = ProfileClient(*self.address)
        self.client.send(p)

    def close(self):
        if self.client is not None:
            self.client.close()
            self.client = None


def _empty(sid, stamp_s, counter):
    return Profile(sid, stamp_s, counter % COUNTER_MODULO, np.zeros((0, 2)), np.zeros(0, bool),
                   np.zeros(0, np.float32))


def _extra(dropped, base):
    return {k: v - base.get(k, 0) for k, v in dropped.items() if v != base.get(k, 0)}


def _tracks(runner):
    return [(t.id, t.kind) for t in runner.analysis.tracks]


def test_three_forged_stamps_on_the_sensors_stream_never_resync_its_clock(twin, tmp_path):
    """Failure 2: three empty S2 frames stamped 1e9, 1e9+0.5, 1e9+1.0 s, sent within
    milliseconds on S2's own connection: the host clock disagrees, so they are dropped as
    implausible_stamp and S2's clock is never re-synced."""
    sim, msgs, clean = twin
    sent = []

    def attack(m, bridge, second):
        if m.sensor_id == "S2" and m.stamp_s > 1.5 and not sent:
            for k in range(3):
                bridge.send(_empty("S2", 1e9 + 0.5 * k, m.counter + 1 + k))
            sent.append(3)

    r = serve(sim, msgs, tmp_path, attack)
    assert sent == [3]
    assert r.gates.steps == []
    assert _extra(r.analysis.dropped, clean.analysis.dropped) == {"implausible_stamp": 3}
    assert r.analysis.fusion.profiles_fused == clean.analysis.fusion.profiles_fused
    assert _tracks(r) == _tracks(clean)
    assert stream_verdicts(r.stream_shares(), 0.25) == (EXIT_OK, [])


def test_a_counter_collision_from_a_second_connection_is_a_duplicate_source(twin, tmp_path):
    """Failure 3 from another connection: an empty S3 frame with the twin's next counter before
    each real S3 frame; all dropped as duplicate_source, every real S3 profile fused."""
    sim, msgs, clean = twin
    n = []

    def attack(m, bridge, second):
        if m.sensor_id == "S3" and m.stamp_s > 0.5:
            second.send(_empty("S3", m.stamp_s - 0.001, m.counter))
            n.append(1)

    r = serve(sim, msgs, tmp_path, attack)
    assert len(n) > 20
    assert _extra(r.analysis.dropped, clean.analysis.dropped) == {"duplicate_source": len(n)}
    assert r.analysis.fusion.profiles_fused == clean.analysis.fusion.profiles_fused
    assert _tracks(r) == _tracks(clean)
    (dup,) = r.stream_report()["duplicate_sources"]
    assert dup["sensor"] == "S3" and dup["frames_dropped"] == len(n)
    assert stream_verdicts(r.stream_shares(), 0.25) == (EXIT_OK, [])


def test_a_counter_collision_on_the_sensors_own_stream_fails_the_run_naming_it(twin, tmp_path):
    """Failure 3 on S3's own connection (the one stream it has): the real S3 frames are
    duplicate_counter, and though the robot's thousands of states outnumber them, S3's own
    lost share fails the run (exit 1) with a line naming S3."""
    sim, msgs, clean = twin
    n: list = []
    r = serve(sim, msgs, tmp_path, _s3_collision(n))
    extra = _extra(r.analysis.dropped, clean.analysis.dropped)
    assert extra["duplicate_counter"] == len(n) and extra["empty_profile"] == len(n)
    shares = r.stream_shares()
    assert shares["S1"]["kept"] == clean.stream_shares()["S1"]["kept"]
    code, lines = stream_verdicts(shares, 0.25)
    assert code == EXIT_MISSED and len(lines) == 1 and lines[0].startswith("stream S3 lost ")
    assert shares["S3"]["received"] == clean.stream_shares()["S3"]["received"] + len(n)
    assert len(_tracks(r)) <= len(_tracks(clean))


def test_a_flood_of_plausible_frames_from_a_second_source_is_dropped(twin, tmp_path):
    """Failure 4: a second connection claims S2 with copies of its real frames (points and
    all), four per real frame, counters from 3,000,000: all dropped as duplicate_source, the
    first stream kept and fused whole, no phantom track."""
    sim, msgs, clean = twin
    n = []

    def attack(m, bridge, second):
        if m.sensor_id == "S2" and m.stamp_s > 0.5:
            for k in range(4):
                c = 3_000_000 + len(n)
                second.send(dataclasses.replace(m, stamp_s=m.stamp_s + 0.002 * k, counter=c))
                n.append(1)

    r = serve(sim, msgs, tmp_path, attack)
    assert len(n) > 80
    assert _extra(r.analysis.dropped, clean.analysis.dropped) == {"duplicate_source": len(n)}
    assert r.analysis.fusion.profiles_fused == clean.analysis.fusion.profiles_fused
    assert _tracks(r) == _tracks(clean)
    report = r.stream_report()
    assert report["counters"] == {}
    assert [d["frames_dropped"] for d in report["duplicate_sources"]] == [len(n)]


def _s3_collision(n):
    def attack(m, bridge, second):
        if m.sensor_id == "S3" and m.stamp_s > 0.5:
            bridge.send(_empty("S3", m.stamp_s - 0.001, m.counter))
            n.append(1)
    return attack


def test_dm2_monitor_live_exits_1_naming_the_blinded_sensor(twin, tmp_path):
    """The command itself: the collision on S3's own stream ends `dm2 monitor --live` with
    exit 1 and a line naming S3; the robot's and the other profilers' streams pass."""
    import threading

    from typer.testing import CliRunner

    from dm2.cli.main import app
    from twin.stream.serve import write_cell_files

    sim, msgs, _ = twin
    ports = []
    for kind in (socket.SOCK_DGRAM, socket.SOCK_STREAM):
        with socket.socket(socket.AF_INET, kind) as s:
            s.bind(("127.0.0.1", 0))
            ports.append(s.getsockname()[1])
    egm, prof = ("127.0.0.1", ports[0]), ("127.0.0.1", ports[1])
    cell = write_cell_files(sim, tmp_path / "cell", egm=f"127.0.0.1:{ports[0]}",
                            profiles=f"127.0.0.1:{ports[1]}", speed=SPEED,
                            live={"idle_stop_s": 1.0})
    n: list = []
    sender = threading.Thread(target=send, args=(msgs, {"egm": egm, "profiles": prof},
                                                 _s3_collision(n)))
    sender.start()
    try:
        res = CliRunner().invoke(app, ["monitor", "--live", str(cell), "--out",
                                       str(tmp_path / "out")])
    finally:
        sender.join(60)
    text = " ".join(res.output.split())
    assert res.exit_code == 1, text
    assert "cell.toml: stream S3 lost " in text
    assert "stream S1" not in text and "stream S2" not in text and "stream robot" not in text
    assert f"dropped {len(n):,} messages: duplicate_counter" in text
