"""Toolpath planning: slicing, raster infill, contours, overhangs, linking, file formats."""

from dm2.toolpath.generator import generate_toolpath

__all__ = ["generate_toolpath"]
