"""Monitor an MCAP recording with the pipeline and write its run folder (report.json, index.html).

    python examples/monitor_recording.py RUN.mcap OUT_DIR
    (a recording: `dm2 simulate scenarios/suites/smoke/bump.toml --out RUN.mcap`)
"""

import sys
import tomllib

from dm2.core.config import MonitorConfig, ProcessConfig
from dm2.io.recording import read_recording
from dm2.pipeline.pipeline import Pipeline

recording_path, out_dir = sys.argv[1], sys.argv[2]
recording = read_recording(recording_path)
# the twin attaches its scenario; a real cell's settings would come from its cell file
scenario = tomllib.loads(recording.scenario_toml or "")
monitor = MonitorConfig(**scenario.get("monitor", {}))
process = ProcessConfig(**scenario.get("process", {}))
plate_size_mm = scenario.get("cell", {}).get("plate_size_mm", (120.0, 120.0, 6.0))

pipeline = Pipeline(recording.calibration, monitor, process, plate_size_mm=plate_size_mm,
                    toolpath=recording.toolpath)
pipeline.run(recording.messages())
report = pipeline.write_outputs(out_dir, inputs=[recording_path], command="monitor_recording.py")
print(f"{len(pipeline.results)} layers, {len(report['tracks'])} track(s) -> {out_dir}/index.html")
for track in report["tracks"]:
    print(f"track {track['id']}: {track['kind']} from layer {track['first_layer']}")
