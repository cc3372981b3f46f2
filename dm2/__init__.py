"""3D-DM2: in-process 3D deviation mapping and defect monitoring for robotic cold spray AM."""

__version__ = "0.1.0"
