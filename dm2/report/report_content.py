"""What a run's report says besides its layer results and tracks (:func:`dm2.report.write_report`),
in one value: the live monitor hands it to the report child process as it is."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from dm2.core.config import ExpectConfig
    from dm2.core.messages import Toolpath


@dataclass(frozen=True)
class ReportContent:
    """The report's inputs beside the results and tracks; every one optional.

    Attributes
    ----------
    config_toml : the resolved configuration text (``dm2.core.toml_write.dump_toml``), written
        as-is to config.toml
    dropped : drops by reason, copied into report.json
    timing : stage times [s], copied into report.json (the report's own write time is added)
    meta : run description copied into report.json
    sections : further top-level report.json sections, e.g. ``realtime`` (alarms, latency)
        and ``reconstruction`` (distance to the true surface per layer)
    fault_truth : dict/list of injected faults to compare the tracks with
    expect : dm2.core.config.ExpectConfig to check
    map_layers : layers to render as PNG deviation maps (None: see
        dm2.report.contents.default_map_layers)
    limit_mm : colour range of the deviation maps and PLY colours [mm]
    toolpath : dm2.core.messages.Toolpath for the planned outline on the maps (None: the
        reference's half-height contour)
    """

    config_toml: str | None = None
    dropped: dict | None = None
    timing: dict | None = None
    meta: dict | None = None
    sections: dict | None = None
    fault_truth: dict | list | None = None
    expect: ExpectConfig | None = None
    map_layers: list[int] | None = None
    limit_mm: float = 1.0
    toolpath: Toolpath | None = None
