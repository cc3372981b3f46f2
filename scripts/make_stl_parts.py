"""Write the shipped STL parts of the regression suite (scenarios/stl/), reproducibly.

* ``plate_with_hole.stl``: a 30 x 24 mm plate, 2.4 mm high, with a 10 mm round hole whose
  centre sits 4 mm right of the plate's centre (the hole's wall is 6 mm from the right edge).
* ``bracket_thin_wall.stl``: an L-shaped bracket 30 x 24 mm, 2.4 mm high: a 10 mm wide base
  leg along x and a 5 mm thin wall along y at its left end.

Run: ``python scripts/make_stl_parts.py`` (from the repository root).
"""

from __future__ import annotations

from pathlib import Path

import shapely
import trimesh
from shapely.geometry import Polygon

OUT = Path(__file__).resolve().parent.parent / "scenarios" / "stl"
HEIGHT_MM = 2.4


def plate_with_hole() -> trimesh.Trimesh:
    outline = shapely.box(-15.0, -12.0, 15.0, 12.0)
    hole = shapely.Point(4.0, 0.0).buffer(5.0, quad_segs=16)
    return trimesh.creation.extrude_polygon(outline.difference(hole), HEIGHT_MM)


def bracket_thin_wall() -> trimesh.Trimesh:
    shape = Polygon([(-15.0, -12.0), (15.0, -12.0), (15.0, -2.0), (-10.0, -2.0),
                     (-10.0, 12.0), (-15.0, 12.0)])
    return trimesh.creation.extrude_polygon(shape, HEIGHT_MM)


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    for name, mesh in (("plate_with_hole", plate_with_hole()),
                       ("bracket_thin_wall", bracket_thin_wall())):
        assert mesh.is_watertight, name
        mesh.export(OUT / f"{name}.stl")


if __name__ == "__main__":
    main()
