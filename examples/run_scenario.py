"""Simulate a scenario on the twin and monitor it with the pipeline: the tracks it finds.

    python examples/run_scenario.py [SCENARIO]   # default: the smoke suite's 1.2 mm bump
"""

import sys

from dm2.core.config import load_scenario
from dm2.pipeline.pipeline import Pipeline
from scenarios import resolve_scenario, scenario_dir
from twin.stream.simulate import Simulation  # importing the twin types its scenario sections

name = sys.argv[1] if len(sys.argv) > 1 else str(scenario_dir() / "suites/smoke/bump.toml")
scenario = load_scenario(resolve_scenario(name))
sim = Simulation(scenario)  # the robot cell, the spray and three profilers
pipeline = Pipeline(sim.calibration, scenario.monitor, scenario.process,
                    plate_size_mm=scenario.cell.plate_size_mm, toolpath=sim.toolpath)
results = pipeline.run(sim.messages())  # Profile, RobotState and LayerMark messages

for result in results:
    print(f"layer {result.layer}: {len(result.regions)} region(s)")
for track in pipeline.tracks:
    if track.confirmed:
        last = track.history[-1]
        x_mm, y_mm = last["centroid_O_mm"][:2]
        print(f"track {track.id}: {track.kind} from layer {track.first_layer} at "
              f"({x_mm:.1f}, {y_mm:.1f}) mm, {last['area_mm2']:.1f} mm², "
              f"{last['max_deviation_mm']:+.2f} mm")
