"""Numerical tolerances of dm2, twin and calib, in one place.

Each constant says what it guards and its unit. The values are part of the bit-for-bit
contract of the kernels (ARCHITECTURE.md): numba freezes a module-level float at compile time,
so a kernel that imports one of these computes exactly what it computed with the literal.
Changing a value changes results; do it on purpose, never to make a number pass.
Model parameters (widths, thresholds a user can set) do not live here: they are configuration.
The TSDF kernels (``dm2/fusion/tsdf/``) keep their own constants next to the field.
"""

# --- divisions -------------------------------------------------------------------------------

DIVISOR_FLOOR = 1e-12
"""Floor of a norm, length, area or scale used as a divisor, so a degenerate one (zero-length
segment, zero-area face, empty column) gives a finite quotient [unit of the divisor]."""

TINY_DIVISOR_FLOOR = 1e-300
"""Smallest positive floor of a divisor: keeps a quotient finite without changing any
representable non-zero divisor [unit of the divisor]."""

SQUARED_LENGTH_FLOOR_MM2 = 1e-24
"""Floor of a squared segment length in a projection onto the segment [mm^2]."""

RATIO_FLOOR = 1e-9
"""Floor of the reference value of a relative change or a normalisation (a mean area, the
previous layer's area, a colour-scale limit) [unit of the reference value]."""

# --- zero tests ------------------------------------------------------------------------------

NEAR_ZERO = 1e-12
"""A magnitude below this is zero in a branch test: a vanishing rotation axis, a degenerate
quadratic, a direction parallel to a grid axis, a zero determinant [unit of the value]."""

RELATIVE_ZERO = 1e-12
"""Relative size below which a term of a root formula counts as zero, or a root as on the
interval end [dimensionless, relative to the other term]."""

SMALL_ROTATION_RAD = 1e-8
"""Rotation angle below which the closed forms of SO(3) switch to their series [rad]."""

UNIT_NORM_TOL = 1e-6
"""Largest deviation from 1 of a norm that must be 1 (unit axes, quaternions, the columns of a
rotation, ``|R^T R - I|``) [dimensionless]."""

RELATIVE_LENGTH_ZERO = 1e-6
"""A vector shorter than this times a typical edge length is a zero vector [dimensionless]."""

# --- geometry --------------------------------------------------------------------------------

SAME_POINT_MM = 1e-9
"""Two points closer than this are the same point; a ray parameter below it is the ray's own
origin; a segment shorter than it does not move [mm]."""

SAME_ANGLE_RAD = 1e-9
"""Two angles closer than this are the same angle; slack on joint limits and angle bounds [rad]."""

SAME_TIME_S = 1e-9
"""Two stamps closer than this are the same instant [s]."""

STRAIGHT_TURN_RAD = 1e-7
"""A path turning by less than this at a vertex runs straight through it [rad]."""

TURN_EPS_RAD = 1e-6
"""A polyline vertex turning by less than this has no fillet; a turn within it of pi is a
reversal [rad]."""

FACING_COS = 1e-9
"""A surface faces a ray when the cosine between its normal and the way back exceeds this
[dimensionless]."""

DOWNWARD_COS = 1e-6
"""A ray points down into a height map when its z component is below minus this
[dimensionless, unit axis]."""

OCCLUSION_SLACK_MM = 1e-6
"""A hit this far short of a segment's end still counts as reaching the end (the surface point
itself is not its own occluder) [mm]."""

GEOMETRY_SLACK_MM = 1e-3
"""Slack of a containment or overlap test between polygons [mm]."""

SIMPLIFY_MM = 1e-4
"""Tolerance of the polygon simplification that drops collinear section vertices [mm]."""

GRID_FRACTION_TOL = 1e-4
"""A vertex within this fraction of a voxel of a block face lies on it; vertices within it of
each other are one vertex [voxels]."""

STILL_POSE_MM = 1e-3
"""A transform whose translation moves less than this over a recording is static [mm]."""

STILL_POSE_RAD = 1e-6
"""A transform whose rotation turns less than this over a recording is static [rad]."""

BUILT_HEIGHT_MM = 1e-3
"""A height-map cell whose height (or deviation) exceeds this in magnitude is built [mm]."""

# --- counts and rounding ---------------------------------------------------------------------

ROUNDING_SLACK = 1e-9
"""Relative slack in a floor, ceil or equality of a count of steps, so that an exact multiple
that rounding put a hair off is not counted one up or down [dimensionless]."""

INTERVAL_NUDGE = 1e-9
"""Fraction of a parameter interval by which a probe point is moved inside it, and the interval
length below which its midpoint is used [dimensionless / unit of the parameter]."""
