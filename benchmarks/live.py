"""Benchmark: live end-to-end latency, a profile arriving on the socket -> its voxels fused.

The twin's pad stream is generated first, then sent over loopback like the cell sends it (EGM
datagrams over UDP, profile frames over TCP) paced at a multiple of the rig's rate (at 10x,
3 x 10 Hz profiles and 250 Hz robot states become 300 profiles/s and 2,500 states/s); the live
runner receives, aligns, records to MCAP (on its recorder thread) and fuses with the real
pipeline. The latency of each fused profile runs from the moment its last byte was read from
the socket to the end of the fusion call that integrated it. Goal: p99 <= 20 ms at 10x. Only
profiles fused while the stream runs have a latency; the count line says how many were fused
only when the run ended (the last few: no robot state after their stamp) and what was dropped
by reason (``empty_profile``: no valid point; the twin's pad stream has a few). The percentiles
are over the profiles the plausibility gates passed on arrival; the few they held first (each
source's first ``stamp_seed`` profiles wait for the clock seed: at 10x two of the pad's
profile periods, 20 ms, for the first) are counted and their longest latency printed on a line
of their own, as a start-up figure: in a 1 s stream they alone would make the p99.

Besides the percentiles it prints where the slowest 1% of profiles spent their time (in the
inbox, i.e. behind the loop's other work or the loop waiting for the interpreter lock, or after
it: waiting for the robot state after their stamp, for their batch, fusion), the load average
of the machine (figures are only comparable at similar loads: the machine is shared), the
pipeline load (seconds the live loop spent handling messages and catching up per second of
stream: above 1 the pipeline cannot keep up with the arrival rate and latency grows with the
backlog) and the longest single step (a layer end copies the boxes of the surface chunks
touched in the last fraction of a second, which the session's worker meshes along with the
layer analysis; the reference, real-time comparison and pre-meshing of the other chunks run
when the inbox is empty; interim reports are written by a child process). Prints the median
over runs, after one full warm-up run so numba's cached kernels are loaded before anything is
timed.

With ``--view`` the live 3D view (:class:`dm2.view.live.LiveView`) follows every run with a
client connected and subscribed throughout, so the figures include what serving the view costs:
``--view-client chromium`` (default) a headless Chromium (Debian's ``chromium``; on this machine
it also renders the scene in software, on the same cores), ``--view-client socket`` a plain
websocket client in another process that receives every scene message and draws nothing.

With ``--foxglove`` each speed is run twice as often, alternating: without a Foxglove client
and with the live Foxglove server (:class:`dm2.view.foxglove_live.FoxgloveLive`) following the
run and a Foxglove WebSocket client in another process subscribed to every channel it
advertises (it receives every message and draws nothing); both p99s are printed on one line.

Run: .venv/bin/python benchmarks/live.py [--runs 3] [--seconds 30] [--speeds 10[,3,1]]
    [--view [--view-client chromium|socket]] [--foxglove]
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

if sys.path and Path(sys.path[0]).resolve() == Path(__file__).resolve().parent:
    sys.path.pop(0)  # keep benchmarks/ off the path so `twin` resolves to the package

from dm2.core.config import load_scenario  # noqa: E402
from dm2.core.messages import LayerMark, Profile, RobotState  # noqa: E402
from dm2.live.config import load_cell_file  # noqa: E402
from dm2.live.egm_source import encode_egm_robot  # noqa: E402
from dm2.live.runner import LiveRunner  # noqa: E402
from dm2.live.tcp_frames import encode_frame  # noqa: E402
from dm2.live.tcp_profiles import ProfileClient  # noqa: E402
from scenarios import resolve_scenario  # noqa: E402


def wire_stream(msgs):
    """(stamp, kind, payload bytes) ready to send: EGM datagrams and profile frames."""
    out, layer = [], None
    for m in msgs:
        if isinstance(m, LayerMark):
            layer = m.layer
        elif isinstance(m, RobotState):
            out.append((m.stamp_s, "egm", encode_egm_robot(
                m.seq, round(m.stamp_s * 1000), m.joints_rad, m.T_B_F, stamp_s=m.stamp_s,
                layer=layer)))
        elif isinstance(m, Profile):
            out.append((m.stamp_s, "prof", encode_frame(m)))
    return out


def one_run(cell, wire, speed: float, folder: Path, view=None, fox=None) -> dict:
    """Stream ``wire`` at ``speed`` into a live runner; latencies [ms] and load figures.
    ``fox``: a FoxgloveLive server that follows the run."""
    runner = LiveRunner(cell, folder, record=True)
    if fox is not None:
        fox.attach(runner.analysis.pipeline)
        runner.analysis.layer_listeners.append(fox.on_layer)
    if view is not None:
        pipeline = runner.analysis.pipeline
        view.pose_source = lambda: pipeline.last_T_B_F
        runner.analysis.layer_listeners.append(view.on_layer)
    addr = runner.open_sources()
    span = {}

    def send():
        udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        bridge = ProfileClient(*addr["profiles"])
        t0, s0 = time.monotonic(), wire[0][0]
        try:
            for stamp, kind, data in wire:
                delay = t0 + (stamp - s0) / speed - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                if kind == "egm":
                    udp.sendto(data, addr["egm"])
                else:
                    bridge.send_bytes(data)
        finally:
            span["s"] = time.monotonic() - t0
            udp.close()
            bridge.close()

    th = threading.Thread(target=send)
    th.start()
    runner.run(idle_stop_s=0.5, max_duration_s=600)
    th.join()
    drops = {k: v for k, v in runner.analysis.dropped.items() if k != "out_of_range"}
    held = np.array(runner.held_by_gates, dtype=bool)
    return {"lat_ms": np.array(runner.latencies_s)[~held] * 1e3,
            "inbox_ms": np.array(runner.inbox_waits_s)[~held] * 1e3,
            "held_ms": np.array(runner.latencies_s)[held] * 1e3, "load": runner.busy_s / span["s"],
            "max_step_ms": runner.max_step_s * 1e3, "at_end": runner.fused_at_end,
            "drops": drops}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=30.0, help="process seconds streamed")
    ap.add_argument("--speeds", default="10", help="comma-separated multiples of the rig rate")
    ap.add_argument("--view", action="store_true", help="serve the live 3D view with a "
                    "client connected to it")
    ap.add_argument("--view-client", choices=("chromium", "socket"), default="chromium")
    ap.add_argument("--foxglove", action="store_true", help="also run each speed with the "
                    "live Foxglove server and a client subscribed to all its channels, and "
                    "print both p99s")
    args = ap.parse_args()
    speeds = [float(v) for v in args.speeds.split(",")]
    load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    print(f"load average before the runs (1, 5, 15 min): {load} on {os.cpu_count()} cores",
          flush=True)
    from twin.stream.serve import write_cell_files
    from twin.stream.simulate import Simulation

    sc = load_scenario(resolve_scenario("pad")).model_copy(update={"duration_s": args.seconds})
    sim = Simulation(sc)
    wire = wire_stream(list(sim.messages()))
    n_prof = sum(1 for w in wire if w[1] == "prof")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # the cell file a rehearsal at this speed gets (`dm2 serve-twin --write-cell`): clock
        # band and reorder window widened by the speed-up, the real cell's wall-clock margins
        cells = {speed: load_cell_file(write_cell_files(
            sim, tmp / f"cell{speed:g}", "127.0.0.1:0", "127.0.0.1:0", speed=speed))
            for speed in speeds}
        view = browser = None
        if args.view:
            view, browser = open_view(cells[speeds[0]], tmp / "chromium", args.view_client)
        one_run(cells[speeds[0]], wire, speeds[0], tmp / "warmup", view)
        if args.foxglove:
            for speed in speeds:
                foxglove_pair(cells[speed], wire, speed, tmp, args.runs)
            return
        for speed in speeds:
            runs = [one_run(cells[speed], wire, speed, tmp / f"run{speed:g}_{k}", view)
                    for k in range(args.runs)]
            p50 = median([np.percentile(r["lat_ms"], 50) for r in runs])
            p99 = median([np.percentile(r["lat_ms"], 99) for r in runs])
            seen = f" with the 3D view open ({args.view_client} client)" if view else ""
            print(f"live latency{seen}, socket -> fused, "
                  f"pad stream at {speed:g}x, load average "
                  f"{os.getloadavg()[0]:.2f} "
                  f"({n_prof / args.seconds * speed:.0f} profiles/s, "
                  f"{median([len(r['lat_ms']) for r in runs]):.0f} fused per run, not held "
                  f"by the gates): "
                  f"p50 {p50:.2f} ms, p99 {p99:.2f} ms; pipeline load "
                  f"{median([r['load'] for r in runs]):.2f} s per s of stream, longest step "
                  f"{median([r['max_step_ms'] for r in runs]):.0f} ms (median of {args.runs} "
                  f"runs; goal p99 <= 20 ms at 10x)", flush=True)
            tail = [tail_split(r) for r in runs]
            print(f"  the slowest 1% per run: {median([t[0] for t in tail]):.1f} ms on average, "
                  f"of which {median([t[1] for t in tail]):.1f} ms in the inbox (the loop busy "
                  f"with earlier messages or deferred work, or waiting for the interpreter "
                  f"lock) and {median([t[2] for t in tail]):.1f} ms from "
                  f"leaving it to fused (waiting for a robot state after the profile's stamp, "
                  f"for the batch, fusion)", flush=True)
            held = [r["held_ms"] for r in runs]
            print(f"  start-up: profiles the gates held for the clock seed before passing them "
                  f"{[len(h) for h in held]}, their longest latency "
                  f"{median([h.max() if len(h) else 0.0 for h in held]):.1f} ms (not in the "
                  f"percentiles)", flush=True)
            print(f"  of {n_prof} profiles sent: fused while streaming "
                  f"{[len(r['lat_ms']) + len(r['held_ms']) for r in runs]}, fused at the end "
                  f"of the stream (no "
                  f"robot state after them) {[r['at_end'] for r in runs]}, dropped "
                  f"{[r['drops'] for r in runs]}", flush=True)
        if view is not None:
            print(f"  3D view: {view.updates} layer updates sent to a {args.view_client} client",
                  flush=True)
            browser.terminate()
            browser.wait(10)
            view.close()
            view.stop_server()


FOXGLOVE_CLIENT = """import json, sys
from websockets.sync.client import connect
ws = connect(sys.argv[1], max_size=None, subprotocols=["foxglove.sdk.v1"])
print("connected", flush=True)
subscribed = set()
while True:
    try:
        frame = ws.recv()
    except Exception:  # the server stopped: the benchmark is over
        break
    if isinstance(frame, str):
        op = json.loads(frame)
        if op["op"] == "advertise":
            new = [c["id"] for c in op["channels"] if c["id"] not in subscribed]
            subscribed.update(new)
            ws.send(json.dumps({"op": "subscribe",
                                "subscriptions": [{"id": c, "channelId": c} for c in new]}))
            print("subscribed", len(subscribed), flush=True)
"""


def foxglove_pair(cell, wire, speed: float, tmp: Path, runs: int) -> None:
    """``runs`` runs without and ``runs`` with a Foxglove client, alternating; both p99s."""
    import subprocess

    from dm2.core.calibration_io import read_calibration_toml
    from dm2.view.foxglove_live import FoxgloveLive

    fox = FoxgloveLive(read_calibration_toml(cell.calibration), port=0)
    client = subprocess.Popen([sys.executable, "-c", FOXGLOVE_CLIENT, fox.url],
                              stdout=subprocess.PIPE, text=True)
    try:
        if client.stdout.readline().strip() != "connected" \
                or not client.stdout.readline().startswith("subscribed"):
            raise RuntimeError("the Foxglove client never subscribed")
        without, with_client = [], []
        for k in range(runs):
            without.append(one_run(cell, wire, speed, tmp / f"fx{speed:g}_{k}_off"))
            with_client.append(one_run(cell, wire, speed, tmp / f"fx{speed:g}_{k}_on",
                                       fox=fox))
        p99 = [median([np.percentile(r["lat_ms"], 99) for r in rr])
               for rr in (without, with_client)]
        print(f"live latency, socket -> fused, pad stream at {speed:g}x, load average "
              f"{os.getloadavg()[0]:.2f}: p99 {p99[0]:.2f} ms without a Foxglove client, "
              f"{p99[1]:.2f} ms with one connected and subscribed to every channel "
              f"({fox.updates} layer updates sent; median of {runs} runs each, alternated; "
              f"goal p99 <= 20 ms at 10x)", flush=True)
    finally:
        fox.stop_server()
        try:
            client.wait(10)
        except subprocess.TimeoutExpired:
            client.kill()


SOCKET_CLIENT = """import sys
from websockets.sync.client import connect
ws = connect(sys.argv[1], max_size=None, subprotocols=[sys.argv[2]])
print("connected", flush=True)
while True:
    ws.recv()
"""


def open_view(cell, profile: Path, client: str):
    """A LiveView on a free port and a client process connected to it."""
    import subprocess

    import viser

    from dm2.core.calibration_io import read_calibration_toml
    from dm2.view.live import LiveView

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    view = LiveView(read_calibration_toml(cell.calibration), port=port)
    if client == "socket":
        proc = subprocess.Popen([sys.executable, "-c", SOCKET_CLIENT,
                                 view.url.replace("http", "ws"), f"viser-v{viser.__version__}"],
                                stdout=subprocess.PIPE, text=True)
        if proc.stdout.readline().strip() != "connected":
            raise RuntimeError("the websocket client never connected to the 3D view")
        return view, proc
    browser = subprocess.Popen(
        ["chromium", "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
         "--no-first-run", "--disable-background-networking", "--disable-component-update",
         "--disable-sync", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         f"--user-data-dir={profile}", "--remote-debugging-port=0", view.url],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while not view.state()["clients"]:
        if time.monotonic() > deadline:
            raise RuntimeError("the headless browser never connected to the 3D view")
        time.sleep(0.2)
    return view, browser


def tail_split(run: dict) -> tuple[float, float, float]:
    """Mean latency, inbox wait and the rest [ms] of the profiles at or above the p99."""
    lat, inbox = run["lat_ms"], run["inbox_ms"]
    slow = lat >= np.percentile(lat, 99)
    return float(lat[slow].mean()), float(inbox[slow].mean()), float((lat - inbox)[slow].mean())


def median(v) -> float:
    return float(np.median(v))


if __name__ == "__main__":
    main()
