"""Scenario files: YAML bytes through swarmrt.scenario_files.load_scenario (a Scenario or a
ScenarioError naming the file and field). ``python fuzz/fuzz_scenario.py [atheris args]``."""

import sys

from _harness import fuzz

if __name__ == "__main__":
    fuzz("scenario", sys.argv[1:], include=("swarmcore.scenario", "swarmcore.vision_config"))
