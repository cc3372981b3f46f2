"""The ``[monitor.uncertainty]`` table: the error model of dm2.defects.uncertainty."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class UncertaintyConfig(BaseModel):
    """Standard deviations [mm] of the measurement and reference error per vertex, combined in
    quadrature (dm2.defects.uncertainty). The defaults are dm2.defects.uncertainty_fit's fit
    to the fault-free seven-sided part on the twin (12 layers, on the executed reference clock
    the shipped scenarios use; the
    foot of its walls came out no worse than elsewhere, foot_mm 0, and its few poorly observed
    vertices no worse either, gap_mm_per_mm 0; height not fitted, see
    dm2.defects.uncertainty_fit.DEFAULT_EXCLUDE); refit them for a cell of one's own (README:
    "Refitting the uncertainty model")."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    confidence_k: float = Field(3.0, gt=0)  # called a defect only beyond k combined sigmas
    floor_mm: float = Field(0.127, ge=0)  # everywhere: reconstruction and reference floor
    range_mm: float = Field(0.113, ge=0)  # one observation's range noise, / sqrt(weight)
    wall_mm: float = Field(0.515, ge=0)  # at a vertical measured surface (x (1 - |n_z|))
    edge_mm: float = Field(1.36, ge=0)  # at a reference edge / corner (dm2.defects.uncertainty)
    foot_mm: float = Field(0.0, ge=0)  # at the foot of a wall, near the plate
    gap_mm_per_mm: float = Field(0.0, ge=0)  # per mm to the nearest well observed vertex
    height_mm: float = Field(0.0, ge=0)  # reference error per 10 mm deposited (not fitted)
    # relative uncertainty of the plume width (not fitted: a prior). The width follows from the
    # jet's divergence half-angle, which is rarely known better than 5 against 6 deg (+9 %)
    plume_rel: float = Field(0.10, ge=0)
