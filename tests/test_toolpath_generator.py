"""Toolpath generator: layer count, coverage, continuity, edge tilt, speeds, holes, overhangs."""

import numpy as np
import pytest
import shapely
import trimesh
from shapely.geometry import LineString

from dm2.core.config import PartConfig, ToolpathConfig
from dm2.core.messages import KIND_CODE
from dm2.toolpath import generate_toolpath
from dm2.toolpath.slicing import slice_mesh
from scenarios.parts import build_part

PLATE = (120.0, 120.0, 6.0)
INFILL, EDGE, SKIP, OVER = (KIND_CODE[k] for k in ("infill", "edge", "skip", "overhang"))


def _box(w, d, h, centre=(60.0, 60.0)):
    m = trimesh.creation.box(extents=(w, d, h))
    m.apply_translation((centre[0], centre[1], h / 2))
    return m


@pytest.fixture(scope="module")
def seven():
    mesh = build_part(PartConfig(generator="seven_sided", params={"height_mm": 4.0}), PLATE)
    return mesh, {s: generate_toolpath(mesh, ToolpathConfig(strategy=s))
                  for s in ("double", "single")}


@pytest.fixture(scope="module")
def tower():
    mesh = build_part(PartConfig(generator="twisted_tower"), PLATE)
    return mesh, generate_toolpath(mesh, ToolpathConfig())


def _runs(tp, layer, kinds):
    """Polylines of consecutive moves of the given kinds within one layer."""
    ok = np.isin(tp.kind, kinds) & (tp.layer == layer)
    ok[0] = False
    lines, i, n = [], 1, len(tp)
    while i < n:
        if ok[i]:
            j = i
            while j + 1 < n and ok[j + 1]:
                j += 1
            lines.append(LineString(tp.position_O[i - 1:j + 1, :2]))
            i = j + 1
        else:
            i += 1
    return lines


def _coverage(tp, mesh, spacing):
    sliced = slice_mesh(mesh, 0.8)
    out = []
    for k, region in enumerate(sliced.regions):
        lines = _runs(tp, k, [INFILL, OVER])
        covered = shapely.union_all([ln.buffer(spacing / 2) for ln in lines])
        out.append(covered.intersection(region).area / region.area)
    return np.array(out)


def test_box_20x10x4_gives_five_layers_on_the_plate():
    tp = generate_toolpath(_box(20, 10, 4), ToolpathConfig(layer_mm=0.8))
    assert tp.n_layers == 5 and tp.meta["n_layers"] == 5
    assert tp.meta["layer_z_mm"] == pytest.approx([0.0, 0.8, 1.6, 2.4, 3.2])
    np.testing.assert_allclose(tp.position_O[:, 2], tp.layer * 0.8)
    assert np.all(tp.spray_on)


@pytest.mark.parametrize("strategy", ["double", "single"])
def test_infill_covers_each_slice(strategy, seven):
    mesh, tps = seven
    cov = _coverage(tps[strategy], mesh, 2.0)
    assert cov.min() >= 0.98, cov
    cov_box = _coverage(generate_toolpath(_box(20, 10, 4), ToolpathConfig(strategy=strategy)),
                        _box(20, 10, 4), 2.0)
    assert cov_box.min() >= 0.98, cov_box


def test_twisted_tower_full_height_coverage_and_overhang(tower):
    mesh, tp = tower
    assert tp.n_layers == 124  # 62 double layers of 0.8 mm
    cov = _coverage(tp, mesh, 2.0)
    assert cov.min() >= 0.98, (cov.argmin(), cov.min())
    over_layers = np.unique(tp.layer[tp.kind == OVER])
    assert over_layers.size >= 5
    assert over_layers.min() > 0.55 * 124  # only where the tower expands again
    assert np.all(tp.speed_mm_s[tp.kind == OVER] == 12.0)


@pytest.mark.parametrize("strategy", ["double", "single"])
def test_no_jump_without_skip_and_no_zero_moves(strategy, seven):
    tp = seven[1][strategy]
    step = np.linalg.norm(np.diff(tp.position_O, axis=0), axis=1)
    assert step.min() > 1e-6
    assert np.all(tp.kind[1:][step > 1.5 * 2.0] == SKIP)


def test_speeds_match_kinds(seven):
    tp = seven[1]["double"]
    cfg = ToolpathConfig()
    for name, code in KIND_CODE.items():
        assert np.all(tp.speed_mm_s[tp.kind == code] == getattr(cfg.speed_mm_s, name))
    assert set(np.unique(tp.kind)) >= {INFILL, EDGE, SKIP}
    custom = ToolpathConfig(speed_mm_s={"infill": 25, "edge": 20, "overhang": 10, "skip": 80})
    tp2 = generate_toolpath(_box(20, 10, 4), custom)
    assert np.all(tp2.speed_mm_s[tp2.kind == EDGE] == 20.0)
    assert np.all(tp2.speed_mm_s[tp2.kind == SKIP] == 80.0)


@pytest.mark.parametrize("jet", ["away_from_wall", "toward_wall"])
def test_edge_jets_tilted_35_degrees(seven, jet):
    mesh, _ = seven
    tp = generate_toolpath(mesh, ToolpathConfig(strategy="single", contour_jet=jet))
    # single: layer k's contour comes from slice k
    regions = slice_mesh(mesh, 0.8).regions
    edge = np.flatnonzero(tp.kind == EDGE)
    assert edge.size > 100
    a = tp.axis_O[edge]
    tilt = np.degrees(np.arccos(np.clip(a @ [0, 0, -1.0], -1, 1)))
    np.testing.assert_allclose(tilt, 35.0, atol=1e-9)
    h = a[:, :2] / np.linalg.norm(a[:, :2], axis=1)[:, None]
    p = tp.position_O[edge, :2]
    toward = 1.0 if jet == "away_from_wall" else -1.0  # sign of h . (direction to the outline)
    for k in np.unique(tp.layer[edge]):
        sel = tp.layer[edge] == k
        # the jet's horizontal component points at the nearest outline (away from the wall,
        # out of the material) or away from it (from outside, into the wall) ...
        near = shapely.get_coordinates(shapely.shortest_line(shapely.points(p[sel]),
                                                             regions[k].boundary))
        to_outline = near[1::2] - near[0::2]
        assert np.all(toward * np.einsum("ij,ij->i", h[sel], to_outline) > 0)
        # ... and the material lies on the other side of the outline
        inn = p[sel] - toward * 0.5 * h[sel]
        assert shapely.contains_xy(regions[k], inn[:, 0], inn[:, 1]).all()
    box = generate_toolpath(_box(20, 10, 4), ToolpathConfig(strategy="single",
                                                             contour_jet=jet))
    e = box.kind == EDGE
    out = box.position_O[e, :2] + toward * 2.0 * box.axis_O[e, :2] / np.sin(np.radians(35.0))
    assert not shapely.contains_xy(shapely.box(50, 55, 70, 65), out[:, 0], out[:, 1]).any()
    assert np.all(tp.axis_O[tp.kind == INFILL] == [0.0, 0.0, -1.0])
    assert np.array_equal(tp.axis_O[tp.kind == EDGE][:, 2], -np.cos(np.radians(35.0))
                          * np.ones(edge.size))


def test_contour_angle_follows_config():
    tp = generate_toolpath(_box(20, 10, 4), ToolpathConfig(contour_angle_deg=20.0))
    a = tp.axis_O[tp.kind == EDGE]
    np.testing.assert_allclose(np.degrees(np.arccos(-a[:, 2])), 20.0, atol=1e-9)


def test_seven_sided_hollow_is_never_sprayed(seven):
    mesh, tps = seven
    regions = slice_mesh(mesh, 0.8).regions
    holes = [shapely.Polygon(r) for r in shapely.get_parts(regions[0])[0].interiors]
    assert len(holes) == 1
    hole = holes[0]
    for tp in tps.values():
        spray = np.isin(tp.kind, [INFILL, EDGE, OVER])
        xy = tp.position_O[spray, :2]
        assert not shapely.contains_xy(hole, xy[:, 0], xy[:, 1]).any()
        # every move stays out of the hole: spraying ones, and skips go around it
        moves = shapely.linestrings(np.stack([tp.position_O[:-1, :2], tp.position_O[1:, :2]], 1))
        crosses = shapely.intersects(moves, hole.buffer(-0.05))
        assert not crosses.any(), np.flatnonzero(crosses)


def test_overhang_of_a_stepped_part():
    lower = _box(20, 20, 2.4)
    upper = _box(30, 30, 1.6)
    upper.apply_translation((0, 0, 2.4))
    mesh = trimesh.boolean.union([lower, upper], engine="manifold")
    tp = generate_toolpath(mesh, ToolpathConfig(strategy="single"))
    assert tp.n_layers == 5
    base = shapely.box(50, 50, 70, 70)
    for k in range(tp.n_layers):
        sel = (tp.layer == k) & np.isin(tp.kind, [INFILL, OVER])
        sel[0] = False
        i = np.flatnonzero(sel)
        mid = (tp.position_O[i, :2] + tp.position_O[i - 1, :2]) / 2
        far_out = ~shapely.contains_xy(base.buffer(0.6), mid[:, 0], mid[:, 1])
        inside = shapely.contains_xy(base.buffer(0.4), mid[:, 0], mid[:, 1])
        if k == 3:  # first layer of the wider top: everything beyond the base overhangs
            assert far_out.sum() > 50
            assert np.all(tp.kind[i][far_out] == OVER)
            assert np.all(tp.kind[i][inside] == INFILL)
        else:  # the base and the layer above the first wide one are supported
            assert np.all(tp.kind[i] == INFILL)


def test_corners_are_rounded_and_reported(seven):
    tp = seven[1]["single"]
    d = np.diff(tp.position_O[:, :2], axis=0)
    cross = d[:-1, 0] * d[1:, 1] - d[:-1, 1] * d[1:, 0]
    turn = np.degrees(np.abs(np.arctan2(cross, np.einsum("ij,ij->i", d[:-1], d[1:]))))
    spraying = (tp.kind[1:-1] != SKIP) & (tp.kind[2:] != SKIP)
    assert turn[spraying].max() <= 22.5 + 1e-6
    corners = tp.meta["corners"]
    outer = {round(a) for a in corners["angle_deg"]}
    assert {45, 60, 90, 120, 150, 215, 220} <= outer
    assert np.all(tp.kind[corners["index"]] == EDGE)


def test_double_strategy_order_and_crosshatch():
    tp = generate_toolpath(_box(20, 10, 4), ToolpathConfig(strategy="double"))
    for k in (0, 2):
        assert set(np.unique(tp.kind[tp.layer == k])) <= {INFILL, SKIP}
    for k in (1, 3):
        kinds = tp.kind[tp.layer == k]
        first_edge = np.argmax(kinds == EDGE)
        assert np.all(kinds[:first_edge] != EDGE) and np.all(kinds[first_edge:] != INFILL)
    d = np.diff(tp.position_O[:, :2], axis=0)
    long_x = (np.abs(d[:, 0]) > 1.5) & (np.abs(d[:, 1]) < 1e-9) & (tp.kind[1:] == INFILL)
    long_y = (np.abs(d[:, 1]) > 1.5) & (np.abs(d[:, 0]) < 1e-9) & (tp.kind[1:] == INFILL)
    layer = tp.layer[1:]
    assert long_x[layer == 0].sum() > 10 and long_y[layer == 0].sum() == 0
    assert long_y[layer == 2].sum() > 10 and long_x[layer == 2].sum() == 0
    single = generate_toolpath(_box(20, 10, 4), ToolpathConfig(strategy="single"))
    for k in range(5):
        kinds = single.kind[single.layer == k]
        assert (kinds == EDGE).any() and (kinds == INFILL).any()


def test_max_layers_caps_the_path():
    tp = generate_toolpath(_box(20, 10, 4), ToolpathConfig(max_layers=2))
    assert tp.n_layers == 2


def test_empty_or_flat_mesh_is_rejected():
    with pytest.raises(ValueError, match="empty"):
        generate_toolpath(trimesh.Trimesh(), ToolpathConfig())
    with pytest.raises(ValueError, match="half a layer"):
        generate_toolpath(_box(20, 10, 0.3), ToolpathConfig())
