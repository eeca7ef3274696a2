"""Reports from real runs; the page loads in a headless browser and shows its figures."""

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def swarm(*args):
    p = subprocess.run([sys.executable, "-m", "swarm.cli", *args], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout + p.stderr
    return p


def _browser_check(page: Path) -> dict:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.fail("chromium is not installed (scripts/apt-packages.txt lists it; run scripts/setup.sh as root)")
    p = subprocess.run(
        [exe, "--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=8000", "--dump-dom", page.resolve().as_uri()],
        capture_output=True,
        text=True,
        timeout=120,
    )
    body = re.search(r"<body([^>]*)>", p.stdout)
    assert body, p.stderr[-2000:]
    return dict(re.findall(r'data-([a-z-]+)="([^"]*)"', body.group(1)))


def test_report_from_a_sim_run_loads_in_a_browser(tmp_path):
    run = tmp_path / "sim"
    swarm("sim", "scenarios/demo.yaml", "--out", str(run), "--set", "duration_s=15")
    swarm("report", str(run))
    page = run / "report" / "report.html"
    names = {p.name for p in (run / "report").glob("*.png")}
    assert {"nees.png", "gate.png", "schedule.png"} <= names and sum(n.startswith("errors_filter_") for n in names) == 4
    attrs = _browser_check(page)
    assert attrs["errors"] == "0"
    assert attrs["images"] == attrs["images-loaded"] == "7"
    # Self-contained: no external resources.
    assert "src=\"data:image/png;base64," in page.read_text() and "http" not in page.read_text().split("<body")[1]


@pytest.mark.integration
def test_report_from_a_recording_with_faults_marks_them(tmp_path):
    from swarm_harness import run_swarm, scenario

    sc = scenario(n_sats=3, duration_s=12, faults=[{"at_step": 5, "action": "kill-agent", "target": 1}])
    run_swarm(sc, tmp_path / "run")
    swarm("report", str(tmp_path / "run" / "run.mcap"), "--out", str(tmp_path / "rep"))
    html = (tmp_path / "rep" / "report.html").read_text()
    assert "kill-agent" in html
    attrs = _browser_check(tmp_path / "rep" / "report.html")
    assert attrs["errors"] == "0" and attrs["images"] == attrs["images-loaded"] == "6"


@pytest.mark.slow
def test_report_from_a_monte_carlo_folder(tmp_path):
    mc = tmp_path / "mc"
    swarm("mc", "scenarios/demo.yaml", "--runs", "3", "--workers", "2", "--out", str(mc), "--set", "duration_s=8")
    swarm("report", str(mc))
    page = mc / "report" / "report.html"
    assert (mc / "report" / "mc_bars.png").exists()
    text = page.read_text()
    assert text.count("<tr>") >= 3 + 1
    attrs = _browser_check(page)
    assert attrs["errors"] == "0" and attrs["images"] == attrs["images-loaded"] == "1"
