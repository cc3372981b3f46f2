"""`dm2 simulate` then `dm2 monitor` on the pad scenario: every layer's reconstruction against the
twin's per-layer ground truth surface (the part grows while it is scanned)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from dm2.cli.main import app
from dm2.fusion.surface import read_ply

pytest.importorskip("twin.stream.simulate")


@pytest.mark.slow
def test_twin_recording_of_a_growing_pad_is_reconstructed_per_layer(tmp_path):
    runner = CliRunner()
    run = tmp_path / "pad.mcap"
    res = runner.invoke(app, ["simulate", "pad", "--out", str(run), "--duration-s", "30",
                              "--truth", str(tmp_path / "truth")])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["monitor", str(run), "--out", str(tmp_path / "mon")])
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "mon" / "monitor.json").read_text())
    layers = [row["layer"] for row in summary["layers"]]
    assert layers == list(range(len(layers))) and len(layers) >= 3
    for layer in layers:
        truth = trimesh.load(tmp_path / "truth" / f"layer_{layer:03d}.ply", process=False)
        surf = read_ply(tmp_path / "mon" / f"layer_{layer:04d}.ply")
        lo, hi = truth.bounds  # the truth covers a window around the part
        v = surf.vertices_O
        inside = np.all((v[:, :2] > lo[:2] + 1) & (v[:, :2] < hi[:2] - 1), axis=1)
        v = v[inside][:: max(1, inside.sum() // 4000)]
        _, dist, _ = trimesh.proximity.closest_point(truth, v)
        rms = float(np.sqrt(np.mean(dist**2)))
        print(f"layer {layer}: RMS {rms:.3f} mm over {len(v)} vertices")
        assert rms <= 0.25
