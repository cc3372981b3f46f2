"""Digital twin of the cold-spray cell: robot, spray deposition and three laser profilers.

The twin emits exactly what the real cell emits (profiles and robot states); ``dm2`` never
imports it.
"""

from twin import schema as _schema  # noqa: F401  registers the twin's scenario sections
