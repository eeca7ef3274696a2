"""deploy/kuberay/raycluster.yaml: the KubeRay route, on paper (not run here: no Kubernetes).
What can be checked without a cluster: it parses, it is a RayCluster of the project's image
on every pod with the Ray version the project pins, no usage report, the Ray Client port the
docs' `--cluster ray://...:10001` uses, and it says plainly that it was not run."""

from __future__ import annotations

from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def _pinned(name: str) -> str:
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line.lower().startswith(f"{name}=="):
            return line.split("==", 1)[1]
    raise AssertionError(f"{name} not pinned in constraints.txt")


def test_kuberay_manifest_parses_and_runs_the_projects_image():
    path = ROOT / "deploy" / "kuberay" / "raycluster.yaml"
    text = path.read_text()
    assert text.startswith("# NOT RUN HERE"), "the manifest says first that it was not run"
    doc = yaml.safe_load(text)
    assert doc["apiVersion"] == "ray.io/v1" and doc["kind"] == "RayCluster"
    spec = doc["spec"]
    assert spec["rayVersion"] == _pinned("ray")
    head = spec["headGroupSpec"]
    assert head["rayStartParams"]["ray-client-server-port"] == "10001"
    pods = [head["template"]["spec"], *(g["template"]["spec"] for g in spec["workerGroupSpecs"])]
    assert len(pods) >= 2
    for pod in pods:
        for c in pod["containers"]:
            assert c["image"].startswith("swarm-coloc:"), c["image"]
            env = {e["name"]: e["value"] for e in c.get("env", [])}
            assert env.get("RAY_USAGE_STATS_ENABLED") == "0", c["name"]
    for g in [head, *spec["workerGroupSpecs"]]:
        assert g["rayStartParams"]["disable-usage-stats"] == "true"
