"""An estimator from outside the repository: the example package under
examples/estimator-plugin is installed (into a folder of its own, as any package would be
into an environment) and flown by name, in process and as a distributed swarm, with the
same numbers; without it installed, its kind is an error that names the field."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SWARM = [sys.executable, "-m", "swarm.cli"]


@pytest.fixture(scope="module")
def plugin_path(tmp_path_factory) -> Path:
    target = tmp_path_factory.mktemp("plugin")
    p = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--target", str(target),
                        str(ROOT / "examples" / "estimator-plugin")], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    assert (target / "swarm_solo").is_dir() and list(target.glob("swarm_solo-*.dist-info"))
    return target


def _swarm(args, plugin: Path | None, timeout=600):
    env = dict(os.environ)
    if plugin is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(plugin), env.get("PYTHONPATH", "")])
    return subprocess.run([*SWARM, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout, env=env)


def test_an_uninstalled_estimator_is_an_error_naming_the_field(tmp_path):
    p = _swarm(["sim", "scenarios/demo.yaml", "--out", str(tmp_path / "x"), "--set", "estimator.kind=solo"], None)
    assert p.returncode == 2
    assert "estimator.kind: unknown estimator 'solo'" in " ".join(p.stderr.split())


def test_the_example_plugin_flies_in_process_and_its_parameters_are_checked(plugin_path, tmp_path):
    p = _swarm(["sim", "scenarios/demo.yaml", "--out", str(tmp_path / "sim"), "--set", "estimator.kind=solo",
                "--set", "estimator.process_noise_scale=2"], plugin_path)
    assert p.returncode == 0, p.stderr
    s = json.loads((tmp_path / "sim" / "summary.json").read_text())
    assert s["estimator"] == "solo" and s["traffic"]["bytes_per_sat_per_s_mean"] > 0
    assert s["rms"]["self"]["pos_m"] < 0.05
    bad = _swarm(["sim", "scenarios/demo.yaml", "--out", str(tmp_path / "bad"), "--set", "estimator.kind=solo",
                  "--set", "estimator.process_noise_scale=-1"], plugin_path)
    assert bad.returncode == 2 and "estimator.process_noise_scale" in " ".join(bad.stderr.split())


@pytest.mark.integration
@pytest.mark.slow
def test_the_example_plugin_flies_distributed_with_the_in_process_numbers(plugin_path, tmp_path):
    args = ["scenarios/demo.yaml", "--set", "estimator.kind=solo", "--set", "duration_s=20"]
    sim = _swarm(["sim", *args[:1], "--out", str(tmp_path / "sim"), *args[1:]], plugin_path)
    assert sim.returncode == 0, sim.stderr
    run = _swarm(["run", *args[:1], "--out", str(tmp_path / "run"), *args[1:]], plugin_path)
    assert run.returncode == 0, run.stderr[-3000:]
    a = json.loads((tmp_path / "sim" / "summary.json").read_text())
    b = json.loads((tmp_path / "run" / "summary.json").read_text())
    for block in ("rms", "rms_second_half"):
        assert a[block]["self"] == b[block]["self"]
    assert a["nees"] == b["nees"] and a["traffic"] == b["traffic"] and b["estimator"] == "solo"
