"""Crash-safe recording: SIGKILL loses at most about a second; `dm2 recover` restores the rest."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from dm2.cli.main import app
from dm2.core.messages import RobotState
from dm2.io.recording import read_recording
from dm2.live.recorder import LiveRecorder
from dm2.live.recover import recover_recording

WRITER = """
import sys, time
import numpy as np
from dm2.live.recorder import LiveRecorder
from dm2.core.messages import RobotState
w = LiveRecorder(sys.argv[1], attachments={"scenario.toml": b"name = 'k'"}, chunk_s=1.0)
t0 = time.monotonic()
k = 0
while True:
    stamp = time.monotonic() - t0
    w.write(RobotState(stamp, k, np.zeros(6), np.eye(4)))
    sys.stdout.write(f"{k} {stamp:.6f}\\n")
    sys.stdout.flush()
    k += 1
    time.sleep(0.01)
"""


def test_sigkill_loses_at_most_a_second_and_recover_restores_the_rest(tmp_path):
    path = tmp_path / "live.mcap"
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE,
                            text=True, cwd=Path(__file__).resolve().parents[1])
    try:
        lines = []
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:  # wait for 3.5 s of stream
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if float(line.split()[1]) >= 3.5:
                break
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        lines += proc.stdout.readlines()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        proc.stdout.close()
    written = [float(s.split()[1]) for s in lines if len(s.split()) == 2]
    assert written[-1] >= 3.5
    part = tmp_path / "live.mcap.part"
    assert part.is_file() and not path.exists()

    result = CliRunner().invoke(app, ["recover", str(part)])
    assert result.exit_code == 0, result.output
    rec = read_recording(path)
    stamps = np.array([m.stamp_s for m in rec.messages()])
    assert rec.complete and rec.scenario_toml == "name = 'k'"
    assert written[-1] - stamps.max() <= 1.1  # lost at most about a second
    n_expected = sum(1 for s in written if s <= stamps.max() + 1e-6)
    assert len(stamps) == n_expected  # everything up to the last kept message is there
    np.testing.assert_allclose(np.sort(stamps), written[:n_expected], atol=1e-6)


def test_recover_of_a_complete_file_copies_everything(tmp_path):
    w = LiveRecorder(tmp_path / "a.mcap", chunk_s=0.5)
    for k in range(300):
        w.write(RobotState(k * 0.01, k, np.zeros(6), np.eye(4)))
    w.close()
    res = recover_recording(tmp_path / "a.mcap")
    assert res.complete and res.messages == 600  # joint state + tf per robot state
    assert res.out_path.name == "a.recovered.mcap"
    assert len(list(read_recording(res.out_path).messages())) == 300


def test_recover_rejects_non_mcap_and_missing(tmp_path):
    bad = tmp_path / "x.mcap.part"
    bad.write_bytes(b"not mcap at all")
    out = CliRunner().invoke(app, ["recover", str(bad)])
    assert out.exit_code == 2 and "MCAP file" in " ".join(out.output.split())
    out = CliRunner().invoke(app, ["recover", str(tmp_path / "missing.mcap")])
    assert out.exit_code == 2 and "not found" in " ".join(out.output.split())
    assert not (tmp_path / "x.mcap").exists()


def test_recover_of_a_file_cut_before_anything_complete_writes_nothing(tmp_path):
    w = LiveRecorder(tmp_path / "a.mcap", chunk_s=0.5)
    for k in range(300):
        w.write(RobotState(k * 0.01, k, np.zeros(6), np.eye(4)))
    w.close()
    cut = tmp_path / "b.mcap.part"
    cut.write_bytes((tmp_path / "a.mcap").read_bytes()[:200])  # header and schemas only
    out = CliRunner().invoke(app, ["recover", str(cut)])
    assert out.exit_code == 2
    assert "nothing to recover" in " ".join(out.output.split())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.mcap", "b.mcap.part"]


def test_recorder_pushes_chunks_to_disk_within_a_second(tmp_path):
    w = LiveRecorder(tmp_path / "b.mcap", chunk_s=0.2)
    try:
        w.write(RobotState(0.0, 0, np.zeros(6), np.eye(4)))
        size0 = os.path.getsize(tmp_path / "b.mcap.part")
        time.sleep(0.25)
        w.write(RobotState(0.001, 1, np.zeros(6), np.eye(4)))  # wall bound closes the chunk
        assert os.path.getsize(tmp_path / "b.mcap.part") > size0
    finally:
        w.close()


@pytest.mark.parametrize("text, field", [
    ('calibration = "c.toml"\n[live]\negm = "0.0.0.0:6510"\n', "allow_remote"),
    ('calibration = "c.toml"\n[live]\nbogus = 1\n', "live.bogus"),
    ('calibration = "missing.toml"\n', "calibration"),
])
def test_cell_file_errors_name_the_field(tmp_path, text, field):
    from dm2.core.config import ConfigError
    from dm2.live.config import load_cell_file

    (tmp_path / "c.toml").write_text("")
    cell = tmp_path / "cell.toml"
    cell.write_text(text)
    with pytest.raises(ConfigError, match=field) as exc:
        load_cell_file(cell)
    assert str(cell) in str(exc.value)


def test_live_monitor_refuses_a_folder_holding_a_cut_recording(tmp_path):
    """A crashed run's live.mcap.part is what `dm2 recover` needs: a new live run into that
    folder must not truncate it."""
    from dm2.core.config import load_scenario
    from scenarios import resolve_scenario
    from twin.stream.serve import write_cell_files
    from twin.stream.simulate import Simulation

    sim = Simulation(load_scenario(resolve_scenario("pad")).model_copy(
        update={"duration_s": 0.5}))
    cell = write_cell_files(sim, tmp_path / "cell", egm="127.0.0.1:0", profiles="127.0.0.1:0")
    out = tmp_path / "run"
    out.mkdir()
    (out / "live.mcap.part").write_bytes(b"\x89MCAP0\r\n crashed run")
    res = CliRunner().invoke(app, ["monitor", "--live", str(cell), "--out", str(out)])
    assert res.exit_code == 2
    assert "dm2 recover" in " ".join(res.output.split())
    assert (out / "live.mcap.part").read_bytes() == b"\x89MCAP0\r\n crashed run"
