"""The Foxglove layout dm2 ships for its scene (``dm2/report/foxglove-layout.json``).

Built with foxglove-sdk's layout types: a 3D panel (the fused surface coloured by its own
deviation colours, the reference, the raw profiles, the tracks and alarm markers, the frames;
following the plate), a plot of each track's area and height per layer (x: the layer), and
two log panels, the real-time alarms and the verdict with the process findings. Regenerate
the file with ``python -m dm2.report.scene_layout`` (a test checks it is current).
"""

from __future__ import annotations

import json
from pathlib import Path

import foxglove.layouts as fl

from dm2.report import scene_messages as sm

LAYOUT_PATH = Path(__file__).with_name("foxglove-layout.json")


def build_layout() -> fl.Layout:
    points = fl.BaseRendererPointCloudTopicSettings
    topics = {
        sm.TOPIC_SURFACE: points(visible=True, color_mode="rgba-fields", point_size=3.0),
        sm.TOPIC_REFERENCE: points(visible=False, color_mode="flat", flat_color="#a0a0a080",
                                   point_size=2.0),
        sm.TOPIC_PROFILES: points(visible=True, color_mode="rgba-fields", point_size=2.0,
                                  decay_time=1.0),
        sm.TOPIC_TRACKS: fl.BaseRendererSceneUpdateTopicSettings(visible=True,
                                                                 show_outlines=True),
        sm.TOPIC_ALARM_MARKERS: fl.BaseRendererSceneUpdateTopicSettings(visible=True),
    }
    three_d = fl.ThreeDeePanel(title="part, tracks and frames", config=fl.ThreeDeeConfig(
        follow_tf=sm.PLATE, follow_mode="follow-pose", topics=topics))
    stats = f"{sm.TOPIC_TRACK_STATS}"
    plot = fl.PlotPanel(title="tracks per layer", config=fl.PlotConfig(
        x_axis_val="custom", x_axis_label="layer", time_range="all",
        x_axis_path=fl.PlotXAxisPath(value=f"{stats}.layer", enabled=True),
        paths=[fl.PlotSeries(value=f"{stats}.area_mm2", label="track area [mm²]",
                             enabled=True, show_line=False),
               fl.PlotSeries(value=f"{stats}.height_mm", label="track height [mm]",
                             enabled=True, show_line=False, use_right_y_axis=True)]))
    alarms = fl.LogPanel(title="real-time alarms",
                         config=fl.LogConfig(topic_to_render=sm.TOPIC_ALARMS))
    findings = fl.LogPanel(title="verdict and findings",
                           config=fl.LogConfig(topic_to_render=sm.TOPIC_FINDINGS))
    side = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(proportion=2, content=plot), fl.SplitItem(proportion=1, content=alarms),
        fl.SplitItem(proportion=1, content=findings)])
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=2, content=three_d), fl.SplitItem(proportion=1, content=side)]))


def layout_json() -> str:
    """The layout as the shipped file holds it (indented, one trailing newline)."""
    return json.dumps(json.loads(build_layout().to_json()), indent=1) + "\n"


if __name__ == "__main__":
    LAYOUT_PATH.write_text(layout_json(), encoding="utf-8")
