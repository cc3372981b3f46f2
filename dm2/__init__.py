"""3D-DM2: in-process 3D deviation mapping and defect monitoring for robotic cold spray AM."""

from pathlib import Path as _Path

from dm2.core.kernel_cache import key_kernel_caches as _key_kernel_caches

__version__ = "0.1.0"

# before any kernel is defined: a cached kernel is reused only while every file its compiled code
# draws on is unchanged, not only its own (dm2.core.kernel_cache)
_key_kernel_caches((_Path(__file__).parent,), (_Path(__file__).parent,))
