"""Digital twin of the cold-spray cell: robot, spray deposition and three laser profilers.

The twin emits exactly what the real cell emits (profiles and robot states); ``dm2`` never
imports it.
"""

from pathlib import Path as _Path

import dm2 as _dm2
from dm2.core.kernel_cache import key_kernel_caches as _key_kernel_caches

# before any kernel is defined: the twin's cached kernels are reused only while every file of
# the twin and of dm2 (whose functions they may compile in) that compiled code draws on is
# unchanged
_key_kernel_caches((_Path(__file__).parent,), (_Path(_dm2.__file__).parent, _Path(__file__).parent))

from twin import schema as _schema  # noqa: E402, F401  registers the twin's scenario sections
