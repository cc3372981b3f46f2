"""Part generators: watertight, centred on the plate, the documented shapes and errors."""

import numpy as np
import pytest
import shapely
import trimesh

from dm2.core.config import ConfigError, PartConfig
from dm2.toolpath.contours import corner_angles_deg
from dm2.toolpath.slicing import slice_mesh
from scenarios.parts import build_part, seven_sided_outline

PLATE = (120.0, 120.0, 6.0)


@pytest.mark.parametrize("gen", ["box", "pad", "twisted_tower", "seven_sided", "cylinder",
                                 "ring", "tee", "triangle"])
def test_parts_are_watertight_centred_on_the_plate(gen):
    m = build_part(PartConfig(generator=gen), PLATE)
    assert m.is_watertight and m.volume > 0
    lo, hi = m.bounds
    assert lo[2] == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose((lo[:2] + hi[:2]) / 2, [60.0, 60.0], atol=1e-9)


def test_pad_and_box_dimensions():
    np.testing.assert_allclose(build_part(PartConfig(generator="pad"), PLATE).extents,
                               [20, 10, 4])
    box = build_part(PartConfig(generator="box", params={"width_mm": 30, "depth_mm": 12,
                                                           "height_mm": 2.4}), PLATE)
    np.testing.assert_allclose(box.extents, [30, 12, 2.4])
    assert box.volume == pytest.approx(30 * 12 * 2.4)


def test_twisted_tower_twists_narrows_and_overhangs():
    m = build_part(PartConfig(generator="twisted_tower"), PLATE)
    assert m.extents[2] == pytest.approx(99.2)
    sliced = slice_mesh(m, 0.8)
    assert sliced.n_layers == 124
    area = np.array([r.area for r in sliced.regions])
    waist = int(area.argmin())
    assert 0.45 * 124 < waist < 0.65 * 124
    assert area[waist] < 0.45 * area[0] and area[-1] > area[0]
    for k in (20, 40, 60):  # the rounded square's orientation follows twist_deg * z / height
        rect = sliced.regions[k].minimum_rotated_rectangle
        c = np.asarray(rect.exterior.coords)
        edge = c[1] - c[0]
        angle = np.degrees(np.arctan2(edge[1], edge[0])) % 90
        expected = (90.0 * sliced.z_mid_mm[k] / 99.2) % 90
        assert min(abs(angle - expected), 90 - abs(angle - expected)) < 1.0
    grow = [r.difference(below.buffer(0.5)).area
            for below, r in zip(sliced.regions[:-1], sliced.regions[1:], strict=True)]
    assert max(grow[-5:]) > 10.0 and max(grow[:60]) < 1.0


def test_seven_sided_angles_and_hollow():
    outline = seven_sided_outline(70.0)
    angles = corner_angles_deg(np.asarray(outline.exterior.coords))
    np.testing.assert_allclose(np.sort(angles), [45, 60, 90, 120, 150, 215, 220], atol=1e-9)
    assert sum(angles) == pytest.approx(900.0)
    m = build_part(PartConfig(generator="seven_sided", params={"height_mm": 9.6}), PLATE)
    assert m.extents[2] == pytest.approx(9.6)
    region = slice_mesh(m, 0.8).regions[5]
    assert region.geom_type == "Polygon" and len(region.interiors) == 1
    hole = shapely.Polygon(region.interiors[0])
    wall = shapely.Polygon(region.exterior).boundary.distance(hole.boundary)
    assert wall == pytest.approx(13.0, abs=1e-6)


def test_stl_loading_recentres_and_validates(tmp_path):
    good = tmp_path / "good.stl"
    b = trimesh.creation.box(extents=(10, 8, 3))
    b.apply_translation((500, -40, 7))
    b.export(good)
    m = build_part(PartConfig(stl=str(good)), PLATE)
    np.testing.assert_allclose(m.bounds, [[55, 56, 0], [65, 64, 3]], atol=1e-9)
    opened = tmp_path / "open.stl"
    b.update_faces(np.arange(len(b.faces)) > 1)
    b.export(opened)
    with pytest.raises(ConfigError, match=r"open\.stl: part\.stl: mesh is not watertight"):
        build_part(PartConfig(stl=str(opened)), PLATE)
    empty = tmp_path / "empty.stl"
    empty.write_bytes(b"")
    with pytest.raises(ConfigError, match=r"empty\.stl: part\.stl"):
        build_part(PartConfig(stl=str(empty)), PLATE)
    with pytest.raises(ConfigError, match="file not found"):
        build_part(PartConfig(stl=str(tmp_path / "nope.stl")), PLATE)


def test_bad_params_name_the_field():
    with pytest.raises(ConfigError, match=r"part\.params\.radius_mm: unknown parameter"):
        build_part(PartConfig(generator="pad", params={"radius_mm": 2.0}), PLATE)
    with pytest.raises(ConfigError, match=r"part\.params\.height_mm: must be a positive"):
        build_part(PartConfig(generator="box", params={"height_mm": -1.0}), PLATE)
    with pytest.raises(ConfigError, match="does not fit"):
        build_part(PartConfig(generator="box", params={"width_mm": 200.0}), PLATE)


def test_round_parts_ring_tee_and_triangle_have_their_documented_shape():
    cyl = build_part(PartConfig(generator="cylinder"), PLATE)
    np.testing.assert_allclose(cyl.extents, [30, 30, 2.4], atol=1e-9)
    assert cyl.volume == pytest.approx(np.pi * 15**2 * 2.4, rel=1e-3)  # a 256-gon
    ring = build_part(PartConfig(generator="ring", params={"height_mm": 1.6}), PLATE)
    region = slice_mesh(ring, 0.8).regions[0]
    assert region.geom_type == "Polygon" and len(region.interiors) == 1
    assert region.area == pytest.approx(np.pi * (18**2 - 8**2), rel=1e-3)
    assert shapely.Polygon(region.interiors[0]).centroid.distance(shapely.Point(60, 60)) < 1e-6
    tee = build_part(PartConfig(generator="tee"), PLATE)
    np.testing.assert_allclose(tee.bounds, [[45, 50, 0], [75, 70, 2.4]], atol=1e-9)
    assert tee.volume == pytest.approx((30 * 10 + 10 * 10) * 2.4)
    tri = build_part(PartConfig(generator="triangle"), PLATE)
    np.testing.assert_allclose(tri.bounds, [[42, 46, 0], [78, 74, 2.4]], atol=1e-9)
    assert tri.volume == pytest.approx(0.5 * 36 * 28 * 2.4)
    angles = corner_angles_deg(np.asarray(slice_mesh(tri, 0.8).regions[0].exterior.coords))
    base = np.degrees(np.arctan2(28, 18))  # the base angles; the apex takes the rest
    assert sorted(angles[np.abs(angles - 180.0) > 1e-6]) == \
        pytest.approx(sorted([base, base, 180 - 2 * base]), abs=1e-3)


@pytest.mark.parametrize("gen,params,name", [
    ("ring", {"inner_diameter_mm": 40.0}, "inner_diameter_mm"),
    ("tee", {"width_mm": 30.0}, "width_mm"),
    ("cylinder", {"radius_mm": 3.0}, "radius_mm"),
])
def test_new_generators_name_the_bad_parameter(gen, params, name):
    with pytest.raises(ConfigError, match=rf"part\.params\.{name}"):
        build_part(PartConfig(generator=gen, params=params), PLATE)
