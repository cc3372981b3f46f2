"""The signed deviation of a surface mesh from a reference height map, in the work object O.

    python examples/compare_mesh.py [MESH.ply]
    (a mesh in O [mm], e.g. a run folder's layer PLY; default: a 20 x 20 mm block whose right
    half stands 0.5 mm over a 4 mm reference)
"""

import sys

import numpy as np
import trimesh

from dm2.defects.deviation import closest_on_reference
from dm2.reference.height_map import ReferenceMap

CELL_MM = 0.25
x_mm = (np.arange(480) + 0.5) * CELL_MM  # a 120 x 120 mm plate
inside = (x_mm > 50.0) & (x_mm < 70.0)
heights_mm = np.where(inside[:, None] & inside[None, :], 4.0, 0.0)  # a 20 x 20 x 4 mm block
reference = ReferenceMap(heights_mm=heights_mm, cell_mm=CELL_MM)

if len(sys.argv) > 1:
    mesh = trimesh.load(sys.argv[1], force="mesh")
else:
    left = trimesh.creation.box(bounds=[[50.0, 50.0, 0.0], [60.0, 70.0, 4.0]])
    right = trimesh.creation.box(bounds=[[60.0, 50.0, 0.0], [70.0, 70.0, 4.5]])
    mesh = trimesh.util.concatenate([left, right]).subdivide_to_size(0.5)
v = mesh.vertices
points_O = v[(v[:, 2] > 3.99) & (np.abs(v[:, 0] - 60.0) < 9.0) & (np.abs(v[:, 1] - 60.0) < 9.0)]
deviation_mm, _ = closest_on_reference(points_O, reference)  # + over, - under the reference
print(f"{len(points_O)} top vertices: deviation {deviation_mm.min():+.2f} to "
      f"{deviation_mm.max():+.2f} mm")
over = points_O[deviation_mm > 0.25]
print(f"over 0.25 mm: {len(over)} vertices, x {over[:, 0].min():.1f} to {over[:, 0].max():.1f} mm")
