"""The planned outline on the report's maps: the part's outer boundary and its holes."""

from types import SimpleNamespace

import numpy as np

from dm2.report.outline import planned_outline


def _plate_with_hole_toolpath():
    """A 30 x 24 mm raster (2 mm spacing) around a 10 mm hole at (64, 60) mm, with a contour
    pass around the hole, as one layer; a travel move (spray off) between the passes."""
    pts, on = [], []
    for y in np.arange(49.0, 72.0, 2.0):
        half = np.sqrt(max(25.0 - (y - 60.0) ** 2, 0.0))
        spans = ([(46.0, 64.0 - half - 1.0), (64.0 + half + 1.0, 74.0)] if half > 0 else
                 [(46.0, 74.0)])
        for x0, x1 in spans:
            pts += [(x0, y), (x1, y)]
            on += [False, True]
    a = np.linspace(0.0, 2.0 * np.pi, 73)
    ring = np.column_stack([64.0 + 6.0 * np.cos(a), 60.0 + 6.0 * np.sin(a)])
    pts += [tuple(p) for p in ring]
    on += [False] + [True] * (len(ring) - 1)
    xy = np.asarray(pts)
    return SimpleNamespace(position_O=np.column_stack([xy, np.full(len(xy), 1.0)]),
                           spray_on=np.asarray(on), layer=np.zeros(len(xy), np.int32))


def test_planned_outline_has_the_part_and_its_hole():
    outer, hole = planned_outline(_plate_with_hole_toolpath())
    assert np.allclose(outer.min(axis=0), [45.0, 48.0], atol=0.05)
    assert np.allclose(outer.max(axis=0), [75.0, 72.0], atol=0.05)
    r = np.hypot(hole[:, 0] - 64.0, hole[:, 1] - 60.0)  # the contour pass less its half width
    assert 4.7 < r.min() and r.max() < 5.05, (r.min(), r.max())  # (raster ends reach in)


def test_gaps_between_lines_are_not_holes():
    """A raster with staggered line ends, 2.2 mm apart, inside a contour pass: the slots
    between the widened lines are closed at both ends, and still no hole of the part."""
    pts = [(45.5, 48.5), (74.5, 48.5), (74.5, 73.5), (45.5, 73.5), (45.5, 48.5)]
    on = [False, True, True, True, True]
    for k, y in enumerate(np.arange(49.0, 72.0, 2.2)):
        x0, x1 = 46.0 + 0.7 * (k % 3), 74.0 - 0.5 * (k % 2)
        pts += [(x0, y), (x1, y), (x1, y + 2.2)]
        on += [False, True, True]
    xy = np.asarray(pts)
    tp = SimpleNamespace(position_O=np.column_stack([xy, np.ones(len(xy))]),
                         spray_on=np.asarray(on), layer=np.zeros(len(xy), np.int32))
    (outer,) = planned_outline(tp)
    assert outer.min(axis=0)[0] < 46.0 and outer.max(axis=0)[0] > 74.0
