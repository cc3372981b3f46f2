"""Overspray: plate deviations outside the planned outline are their own class unless they are
joined to a defect at the part."""

from types import SimpleNamespace

import numpy as np

from dm2.core.config import MonitorConfig
from dm2.core.messages import KIND_CODE, Toolpath
from dm2.defects.classify import OVERBUILD, OVERSPRAY
from dm2.defects.deviation import layer_deviation
from dm2.defects.footprint import PlannedOutline
from dm2.defects.segment import segment_regions
from dm2.reference.height_map import ReferenceMap

MON = MonitorConfig()


def square_toolpath(lo=50.0, hi=70.0):
    corners = np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi], [lo, lo]])
    pos = np.column_stack([corners, np.zeros(5)])
    far = np.array([[lo, lo, 0.0], [lo - 30.0, lo, 0.0]])  # a skip move out over the plate
    pos = np.vstack([pos, far])
    n = len(pos)
    kind = np.full(n, KIND_CODE["edge"], np.int8)
    kind[-1] = KIND_CODE["skip"]
    return Toolpath(pos, np.tile([0.0, 0.0, -1.0], (n, 1)), np.full(n, 30.0), kind,
                    np.zeros(n, np.int32), np.ones(n, bool), np.zeros(n))


def test_outline_from_depositing_moves_only():
    outline = PlannedOutline.from_toolpath(square_toolpath(), (120.0, 120.0), 0.5)
    d = outline.outside_at(np.array([[50.0, 60.0], [45.0, 60.0], [60.0, 44.0], [30.0, 50.0]]))
    assert d[0] == 0.0  # on the contour
    assert abs(d[1] - 4.0) < 0.6 and abs(d[2] - 5.0) < 0.6  # bead half width 1 mm
    assert d[3] > 15.0  # under the skip move: no planned material


def test_plate_blob_is_overspray_and_wall_defect_stays_overbuild():
    x = np.arange(20.0, 100.0, 0.5)
    xx, yy = np.meshgrid(x, x)
    z = np.zeros_like(xx)
    blob = np.hypot(xx - 30.0, yy - 60.0) < 3.0  # far out on the plate
    z[blob] = 0.8
    wall = (np.abs(yy - 60.0) < 2.0) & (xx > 47.0) & (xx < 53.0)  # across the contour at x=50
    z[wall] = 0.8
    idx = np.arange(xx.size).reshape(xx.shape)
    a, b, c, d = (idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(),
                  idx[1:, 1:].ravel())
    surf = SimpleNamespace(vertices_O=np.column_stack([xx.ravel(), yy.ravel(), z.ravel()]),
                           faces=np.concatenate([np.column_stack([a, b, d]),
                                                 np.column_stack([a, d, c])]),
                           weight=np.full(xx.size, 8.0), normals_O=None)
    ref = ReferenceMap(np.zeros((240, 240)), 0.5, layer=1)
    outline = PlannedOutline.from_toolpath(square_toolpath(), (120.0, 120.0), 0.5)
    dev = layer_deviation(surf, ref, MON, 1, outline=outline)
    code = dev.class_code.reshape(xx.shape)
    inner_blob = np.hypot(xx - 30.0, yy - 60.0) < 2.0
    assert np.all(code[inner_blob] == OVERSPRAY)
    assert np.all(code[wall & (np.abs(yy - 60.0) < 1.0) & (np.abs(xx - 50.0) < 2.5)] == OVERBUILD)
    regions = segment_regions(dev, MON.min_region_area_mm2)
    assert [r.kind for r in regions] == ["overbuild"]
    assert abs(regions[0].centroid_O[0] - 50.0) < 1.0
    # without an outline the blob is an overbuild region of its own
    plain = segment_regions(layer_deviation(surf, ref, MON, 1), MON.min_region_area_mm2)
    assert sorted(r.kind for r in plain) == ["overbuild", "overbuild"]
