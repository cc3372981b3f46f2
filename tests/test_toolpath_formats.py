"""Toolpath files: exact CSV round trip, RAPID round trip to its printed precision."""

import numpy as np
import pytest
import trimesh

from dm2.core.config import ToolpathConfig
from dm2.core.messages import Toolpath
from dm2.toolpath import generate_toolpath
from dm2.toolpath.formats import read_csv, read_rapid, write_csv, write_rapid

FIELDS = ("position_O", "axis_O", "speed_mm_s", "kind", "layer", "spray_on", "zone_mm")


@pytest.fixture(scope="module")
def tp():
    m = trimesh.creation.box(extents=(20, 10, 4))
    m.apply_translation((60.123456789, 60.987654321, 2))
    return generate_toolpath(m, ToolpathConfig(contour_angle_deg=33.3))


def _synthetic():
    rng = np.random.default_rng(3)
    n = 40
    axis = rng.normal(size=(n, 3))
    axis[:, 2] = -np.abs(axis[:, 2]) - 0.5
    axis /= np.linalg.norm(axis, axis=1)[:, None]
    return Toolpath(position_O=rng.uniform(0, 120, (n, 3)), axis_O=axis,
                    speed_mm_s=rng.choice([12.0, 30.0, 50.0, 7.25], n),
                    kind=rng.integers(0, 4, n), layer=np.sort(rng.integers(0, 5, n)),
                    spray_on=rng.random(n) > 0.3, zone_mm=rng.choice([0.0, 1.0, 2.5], n))


@pytest.mark.parametrize("which", ["generated", "synthetic"])
def test_csv_round_trip_is_exact(tmp_path, tp, which):
    src = tp if which == "generated" else _synthetic()
    write_csv(src, tmp_path / "tp.csv")
    back = read_csv(tmp_path / "tp.csv")
    for f in FIELDS:
        assert np.array_equal(getattr(src, f), getattr(back, f)), f
    assert back.meta["n_layers"] == src.n_layers
    header = (tmp_path / "tp.csv").read_text().splitlines()[0]
    assert header == "index,x_mm,y_mm,z_mm,ax,ay,az,speed_mm_s,kind,layer,spray_on,zone_mm"


@pytest.mark.parametrize("which", ["generated", "synthetic"])
def test_rapid_round_trip_to_printed_precision(tmp_path, tp, which):
    src = tp if which == "generated" else _synthetic()
    write_rapid(src, tmp_path / "tp.mod")
    text = (tmp_path / "tp.mod").read_text()
    assert text.startswith("MODULE ") and text.rstrip().endswith("ENDMODULE")
    assert text.count("MoveL ") == len(src)
    back = read_rapid(tmp_path / "tp.mod")
    np.testing.assert_allclose(back.position_O, src.position_O, atol=0.5e-3 + 1e-9)
    np.testing.assert_allclose(back.axis_O, src.axis_O, atol=1e-5)
    for f in ("speed_mm_s", "kind", "layer", "spray_on", "zone_mm"):
        assert np.array_equal(getattr(src, f), getattr(back, f)), f


def test_rapid_quaternion_z_is_the_spray_axis(tmp_path):
    axis = np.array([[0.0, 0.0, -1.0], [np.sin(0.6), 0.0, -np.cos(0.6)]])
    src = Toolpath(np.zeros((2, 3)) + [[0, 0, 0], [1, 0, 0]], axis, [30.0, 30.0], [0, 1],
                   [0, 0], [True, True], [1.0, 1.0])
    write_rapid(src, tmp_path / "a.mod")
    lines = [ln for ln in (tmp_path / "a.mod").read_text().splitlines() if "MoveL" in ln]
    assert "[[0,0,0],[0,1,0,0]" in lines[0]  # 180 deg about x: tool z points down
    assert "v_edge_1,z_path_0,tNozzle\\WObj:=wobjPlate;" in lines[1]


def test_bad_csv_names_file_and_line(tmp_path, tp):
    path = tmp_path / "tp.csv"
    write_csv(tp, path)
    lines = path.read_text().splitlines()
    lines[3] = lines[3].replace("infill", "sprinkle")
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"tp\.csv: line 4: column 'kind'"):
        read_csv(path)
    path.write_text("x,y\n1,2\n")
    with pytest.raises(ValueError, match="line 1: header"):
        read_csv(path)
    with pytest.raises(FileNotFoundError):
        read_csv(tmp_path / "missing.csv")
