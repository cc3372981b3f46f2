"""Damaged and recovered recordings through `dm2 monitor` and `dm2 recover` (issue: bytes
flipped in a middle chunk crashed both with a ZstdError; a flipped bit passed as good; a
recovered file forgot its damage)."""

from __future__ import annotations

import json

import pytest
from mcap.reader import make_reader
from test_monitor_cli import _record
from test_monitor_scene import Scene, make_calibration, raster_run
from typer.testing import CliRunner

from dm2.cli.main import app
from dm2.core.messages import LayerMark
from dm2.io.recording import read_recording

SCENE = Scene(boxes=[((50, 50, 0), (66, 66, 6))])


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    cal = make_calibration()
    msgs, _ = raster_run(SCENE, cal, [((40, 58, 0), (80, 58, 0)), ((80, 64, 0), (40, 64, 0))],
                         step_mm=1.5, noise_mm=0.05, seed=11, t0_s=1.0)
    path = tmp_path_factory.mktemp("dmg") / "full.mcap"
    t_mid = msgs[len(msgs) // 2].stamp_s
    _record(path, msgs, cal, attach=True, marks=[LayerMark(0.0, 0), LayerMark(t_mid, 1)])
    with open(path, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes,
                        key=lambda c: c.chunk_start_offset)
    assert len(chunks) >= 4
    return path, msgs, chunks


def _damaged(recorded, tmp_path, n_bytes: int):
    """A copy with ``n_bytes`` flipped inside the compressed data of the middle chunk."""
    path, _msgs, chunks = recorded
    mid = chunks[len(chunks) // 2]
    data = bytearray(path.read_bytes())
    start = mid.chunk_start_offset + mid.chunk_length // 2
    for i in range(start, start + n_bytes):
        data[i] ^= 0x10
    bad = tmp_path / f"flip{n_bytes}.mcap"
    bad.write_bytes(bytes(data))
    return bad, mid, chunks[len(chunks) // 2 - 1]


@pytest.mark.parametrize("n_bytes", [200, 1])
def test_monitor_stops_at_a_damaged_chunk_and_exits_3_with_a_report(recorded, tmp_path,
                                                                   n_bytes):
    bad, mid, before = _damaged(recorded, tmp_path, n_bytes)
    out = tmp_path / "o"
    res = CliRunner().invoke(app, ["monitor", str(bad), "--out", str(out)])
    assert res.exit_code == 3, res.output
    assert "Traceback" not in res.output
    text = " ".join(res.output.split())
    assert f"from byte {mid.chunk_start_offset:,} on could not be read" in text
    report = json.loads((out / "report" / "report.json").read_text())
    info = report["input"]
    assert info["complete"] is False and info["truncated"] is False
    assert info["stopped_at_byte"] == mid.chunk_start_offset
    # everything up to the damaged chunk was fused: the last stamp is the chunk before's end
    assert info["stopped_at_stamp_s"] == pytest.approx(before.message_end_time / 1e9)
    assert report["layers"] and json.loads((out / "monitor.json").read_text())["input"] == info
    res = CliRunner().invoke(app, ["monitor", str(bad), "--out", str(tmp_path / "o2"),
                                   "--allow-truncated"])
    assert res.exit_code == 0, res.output


def test_recover_stops_at_the_damage_and_the_recovered_file_remembers_it(recorded, tmp_path):
    path, _msgs, chunks = recorded
    bad, mid, before = _damaged(recorded, tmp_path, 200)
    fixed = tmp_path / "fixed.mcap"
    res = CliRunner().invoke(app, ["recover", str(bad), "--out", str(fixed)])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fixed.mcap", "flip200.mcap"]
    end_s = max(c.message_end_time for c in chunks) / 1e9
    lost_s = end_s - before.message_end_time / 1e9
    assert f"last {lost_s:.1f} s lost" in " ".join(res.output.split())
    rec = read_recording(fixed)
    assert rec.recovered == {
        "original_file": "flip200.mcap", "original_bytes": str(bad.stat().st_size),
        "complete": "false", "stopped_at_byte": str(mid.chunk_start_offset),
        "reason": rec.recovered["reason"], "last_stamp_s": f"{before.message_end_time / 1e9:.6f}",
        "lost_s": f"{lost_s:.3f}", "note": f"last {lost_s:.1f} s lost", "intact": True}
    assert "crc" in rec.recovered["reason"].lower() or "zstd" in rec.recovered["reason"].lower()
    out = tmp_path / "o"
    res = CliRunner().invoke(app, ["monitor", str(fixed), "--out", str(out)])
    assert res.exit_code == 3, res.output
    assert (f"was recovered by `dm2 recover` from flip200.mcap ({bad.stat().st_size:,} bytes): "
            f"last {lost_s:.1f} s lost") in " ".join(res.output.split())
    info = json.loads((out / "report" / "report.json").read_text())["input"]
    assert info["complete"] is False and info["recovered"]["lost_s"] == f"{lost_s:.3f}"
    assert info["error"] is None  # the recovered file itself reads to its end
    res = CliRunner().invoke(app, ["monitor", str(fixed), "--out", str(tmp_path / "o2"),
                                   "--allow-truncated"])
    assert res.exit_code == 0, res.output


def test_a_recovered_cut_recording_exits_3_and_a_recovered_whole_one_0(recorded, tmp_path):
    path = recorded[0]
    data = path.read_bytes()
    part = tmp_path / "live.mcap.part"  # what a killed live run leaves
    part.write_bytes(data[: len(data) * 2 // 3])
    res = CliRunner().invoke(app, ["recover", str(part)])
    assert res.exit_code == 0, res.output
    rec = read_recording(tmp_path / "live.mcap")
    assert rec.recovered["complete"] == "false" and rec.recovered["intact"]
    assert rec.recovered["note"] == ("the rest after the last stamp kept lost (its length is "
                                     "not known)")
    res = CliRunner().invoke(app, ["monitor", str(tmp_path / "live.mcap"), "--out",
                                   str(tmp_path / "o")])
    assert res.exit_code == 3, res.output
    assert "was recovered by `dm2 recover` from live.mcap.part" in " ".join(res.output.split())
    res = CliRunner().invoke(app, ["recover", str(path), "--out", str(tmp_path / "w.mcap")])
    assert res.exit_code == 0, res.output
    res = CliRunner().invoke(app, ["monitor", str(tmp_path / "w.mcap"), "--out",
                                   str(tmp_path / "o2")])
    assert res.exit_code == 0, res.output  # nothing was lost
    info = json.loads((tmp_path / "o2" / "monitor.json").read_text())["input"]
    assert info["complete"] is True and info["recovered"]["note"] == "nothing lost"
