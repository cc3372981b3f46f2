"""``dm2 run --foxglove``: a real Foxglove WebSocket client receives the growing part.

The client is the protocol's own client side (the websockets package with the subprotocol
foxglove-sdk's server speaks, ``foxglove.sdk.v1``: Foxglove's WebSocket protocol, formerly
``foxglove.websocket.v1``, which that server no longer accepts): it reads the server's
``advertise``, subscribes to the surface, the tracks and the frames, and decodes the binary
message frames (opcode 1: subscription id, log time, payload) with the schemas the server
advertised. On the short pad run with a 1 mm
bump from layer 2 (tests/test_scene_mcap.py) it receives a point cloud in the plate frame, the
bump's overbuild track as a labelled box, and the frames of the flange, plate, nozzle and
sensors. Also: the server refuses a non-loopback address unless ``allow_remote``.
"""

from __future__ import annotations

import base64
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

websockets = pytest.importorskip("websockets.sync.client")

from test_scene_mcap import bump_scenario  # noqa: E402

SUBPROTOCOL = "foxglove.sdk.v1"
WANTED = ("/dm2/surface", "/dm2/tracks", "/tf")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def decoder(channel: dict):
    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return message_factory.GetMessageClass(
        pool.FindMessageTypeByName(channel["schemaName"])).FromString


def connect(port: int, proc, deadline: float):
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"dm2 run ended early:\n{proc.stdout.read()}")
        try:
            return websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL],
                                      open_timeout=5, max_size=None)
        except OSError:
            time.sleep(0.5)
    pytest.fail("no Foxglove server came up")


def test_a_websocket_client_receives_surface_tracks_and_frames(tmp_path):
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    proc = subprocess.Popen(
        [sys.executable, "-m", "dm2.cli.main", "run", str(bump_scenario(tmp_path)), "--out",
         str(tmp_path / "run"), "--no-record", "--no-scene", "--foxglove",
         "--foxglove-port", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    got: dict[str, list] = {t: [] for t in WANTED}
    try:
        deadline = time.monotonic() + 540
        with connect(port, proc, deadline) as ws:
            assert ws.subprotocol == SUBPROTOCOL
            channels, subs = {}, {}
            while time.monotonic() < deadline:
                frame = ws.recv(timeout=30)
                if isinstance(frame, str):
                    op = json.loads(frame)
                    if op["op"] == "advertise":
                        new = [c for c in op["channels"] if c["topic"] in WANTED]
                        for c in new:
                            sid = len(subs) + 1
                            subs[sid] = (c["topic"], decoder(c))
                            channels[c["topic"]] = c
                        ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": sid, "channelId": channels[t]["id"]}
                            for sid, (t, _) in subs.items()
                            if t in {c["topic"] for c in new}]}))
                    continue
                assert frame[0] == 0x01  # message data
                sid, _log_ns = struct.unpack_from("<IQ", frame, 1)
                topic, decode = subs[sid]
                got[topic].append(decode(frame[13:]))
                boxes = [e for u in got["/dm2/tracks"] for e in u.entities]
                if got["/dm2/surface"] and got["/tf"] and any(
                        {kv.key: kv.value for kv in e.metadata}.get("kind") == "overbuild"
                        for e in boxes):
                    break
            assert {c["schemaName"] for c in channels.values()} == {
                "foxglove.PointCloud", "foxglove.SceneUpdate", "foxglove.FrameTransforms"}
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
    cloud = got["/dm2/surface"][-1]
    assert cloud.frame_id == "plate" and len(cloud.data) // cloud.point_stride > 100
    boxes = [e for u in got["/dm2/tracks"] for e in u.entities]
    bump = [e for e in boxes if {kv.key: kv.value for kv in e.metadata}["kind"] == "overbuild"]
    assert bump, "no overbuild track received"
    pos = bump[-1].cubes[0].pose.position
    size = bump[-1].cubes[0].size
    assert abs(pos.x * 1e3 - 57.0) <= size.x * 1e3 / 2 + 1.0
    assert abs(pos.y * 1e3 - 60.0) <= size.y * 1e3 / 2 + 1.0
    frames = {(t.parent_frame_id, t.child_frame_id) for m in got["/tf"] for t in m.transforms}
    assert frames >= {("flange", "plate"), ("base", "nozzle"), ("base", "S1"), ("base", "S2"),
                      ("base", "S3")}


def test_a_remote_address_needs_allow_remote():
    from dm2.view.foxglove_live import check_host

    assert check_host("127.0.0.1", False) == "127.0.0.1"
    assert check_host("0.0.0.0", True) == "0.0.0.0"
    with pytest.raises(ValueError, match="'0.0.0.0' is not a loopback address"):
        check_host("0.0.0.0", False)


def test_the_cell_file_refuses_a_remote_foxglove_address_without_allow_remote():
    from dm2.live.config import LiveConfig

    with pytest.raises(ValueError, match="foxglove binds 0.0.0.0, not loopback"):
        LiveConfig(foxglove="0.0.0.0:8765")
    assert LiveConfig(foxglove="0.0.0.0:8765", allow_remote=True).foxglove == "0.0.0.0:8765"


def test_live_monitor_serves_foxglove_and_writes_the_scene(tmp_path):
    """``dm2 monitor --live CELL --foxglove`` on the twin served over loopback: the server
    comes up on the cell file's address and goes away at the end; the folder's scene.mcap,
    written from the live recording, holds report.json's tracks and findings."""
    from test_live_rehearsal import pad_with_bump
    from test_scene_mcap import check_tracks_and_findings, read_scene
    from typer.testing import CliRunner

    from dm2.cli.main import app
    from twin.stream.serve import serve_twin, write_cell_files
    from twin.stream.simulate import Simulation

    sc = pad_with_bump(12.0)
    sim = Simulation(sc)
    egm, prof, fox = free_port(), free_port(), free_port()
    cell = write_cell_files(sim, tmp_path / "cell", egm=f"127.0.0.1:{egm}",
                            profiles=f"127.0.0.1:{prof}", speed=10.0,
                            live={"idle_stop_s": 2.0, "foxglove": f"127.0.0.1:{fox}"})
    import threading

    seen = {}

    def serve():
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and "client" not in seen:
            try:  # the monitor's Foxglove server is up before the stream starts
                with websockets.connect(f"ws://127.0.0.1:{fox}", subprotocols=[SUBPROTOCOL],
                                        open_timeout=5) as ws:
                    seen["client"] = json.loads(ws.recv(timeout=10))["op"]
            except OSError:
                time.sleep(0.2)
        seen["served"] = serve_twin(sc, ("127.0.0.1", egm), ("127.0.0.1", prof), speed=10.0,
                                    simulation=sim, connect_timeout_s=60)

    thread = threading.Thread(target=serve)
    thread.start()
    res = CliRunner().invoke(app, ["monitor", "--live", str(cell), "--out",
                                   str(tmp_path / "out"), "--foxglove"])
    thread.join(60)
    assert res.exit_code == 0, res.output
    assert seen["client"] == "serverInfo"
    assert f"ws://127.0.0.1:{fox}" in res.output
    report = json.loads((tmp_path / "out" / "report" / "report.json").read_text())
    assert [(t["id"], t["kind"]) for t in report["tracks"]] == [(1, "overbuild")]
    scene = read_scene(tmp_path / "out" / "scene.mcap")
    check_tracks_and_findings(report, scene, alarms=False)
    # the live report holds no real-time section; the scene has the session's alarms, each
    # one logged to monitor.log too
    # (whether the bump raises a real-time alarm in a 1.2 s live run depends on the host's
    # timing: the scene must hold exactly the ones the run logged)
    logged = (tmp_path / "out" / "monitor.log").read_text().count("real-time: ")
    assert len(scene.get("/dm2/alarms", {"messages": []})["messages"]) == logged
    with pytest.raises(OSError):  # the server is gone with the run
        websockets.connect(f"ws://127.0.0.1:{fox}", subprotocols=[SUBPROTOCOL],
                           open_timeout=2).close()


def test_a_taken_port_is_a_clear_error_before_the_run(tmp_path):
    from typer.testing import CliRunner

    from dm2.cli.main import app

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        res = CliRunner().invoke(app, ["run", "pad", "--out", str(tmp_path / "run"),
                                       "--foxglove", "--foxglove-port", str(port)])
    assert res.exit_code == 2, res.output
    assert f"Foxglove server on 127.0.0.1:{port}" in res.output
    assert "Address already in use" in res.output
    assert not (tmp_path / "run").exists()
