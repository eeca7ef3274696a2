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


_LINKS = ["links.enabled=true", "links.latency.fixed_s=2", "links.latency.speed_of_light=false", "links.loss.model=gilbert_elliott",
          "links.loss.rate=0.3", "links.loss.mean_burst=3"]


def _link_rows(text: str) -> dict:
    """The Links table of a report page: {"i → j" or "all": [sent, delivered, late, lost, dropped, unreachable, bytes, mean, p95]}."""
    table = text.split("<h2>Links</h2>", 1)[1].split("</table>", 1)[0]
    rows = {}
    for tr in re.findall(r"<tr>(.*?)</tr>", table)[1:]:
        cells = re.findall(r"<t[dh]>(.*?)</t[dh]>", tr)
        rows[cells[0]] = cells[1:]
    return rows


def test_report_of_a_sim_run_with_links_has_the_link_section(tmp_path):
    import json

    run = tmp_path / "sim"
    p = swarm("sim", "scenarios/demo.yaml", "--out", str(run), "--set", "duration_s=15", *[a for s in _LINKS for a in ("--set", s)])
    assert "links (all directed links)" in p.stderr  # the end-of-run link table
    swarm("report", str(run))
    names = {p.name for p in (run / "report").glob("*.png")}
    # Per-step events, late measurements, the latency histogram and the queues, as for a recording.
    assert {"links_events.png", "links_late.png", "links_latency.png", "links_queue.png"} <= names
    text = (run / "report" / "report.html").read_text()
    rows = _link_rows(text)
    s = json.loads((run / "summary.json").read_text())
    assert len(rows) == 4 * 3 + 1
    tot = s["links"]["totals"]
    assert [int(x) for x in rows["all"][:7]] == [tot[k] for k in ("sent", "delivered", "delivered_late", "lost", "dropped_queue",
                                                                  "unreachable", "bytes_delivered")]
    assert [int(x) for x in rows["2 → 1"][:7]] == [s["links"]["per_link"][k][2][1] for k in (
        "sent", "delivered", "delivered_late", "lost", "dropped_queue", "unreachable", "bytes_delivered")]
    assert f"{s['late']['used']} used" in text
    attrs = _browser_check(run / "report" / "report.html")
    assert attrs["errors"] == "0" and attrs["images"] == attrs["images-loaded"] == "11"


@pytest.mark.integration
def test_report_of_a_recording_with_links_shows_latencies_and_queues(tmp_path):
    import numpy as np
    from swarm_harness import run_swarm, scenario

    links = {"enabled": True, "latency": {"fixed_s": 1.0, "jitter": {"distribution": "uniform", "scale_s": 1.0}},
             "rate_Bps": 2000.0, "loss": {"model": "bernoulli", "rate": 0.2}}
    sc = scenario(n_sats=3, duration_s=12, links=links)
    rec, summary, _codes, _ = run_swarm(sc, tmp_path / "run")
    swarm("report", str(tmp_path / "run"), "--out", str(tmp_path / "rep"))
    names = {p.name for p in (tmp_path / "rep").glob("*.png")}
    assert {"links_latency.png", "links_events.png", "links_queue.png", "links_late.png"} <= names
    rows = _link_rows((tmp_path / "rep" / "report.html").read_text())
    assert rec.links is not None
    lat = np.array(rec.links.latencies)
    for i, j in ((0, 1), (2, 0)):
        v = lat[(lat[:, 0] == i) & (lat[:, 1] == j), 3]
        assert float(rows[f"{i} → {j}"][7]) == pytest.approx(v.mean(), rel=1e-3)
        assert float(rows[f"{i} → {j}"][8]) == pytest.approx(np.percentile(v, 95), rel=1e-3)
    assert int(rows["all"][1]) == summary["links"]["totals"]["delivered"] == len(lat)
    attrs = _browser_check(tmp_path / "rep" / "report.html")
    assert attrs["errors"] == "0" and attrs["images"] == attrs["images-loaded"] == "10"


def test_tables_say_no_data_and_why_instead_of_nan():
    """A summary with missing errors (a run cut short) prints "no data" and the reason, never nan."""
    from rich.console import Console

    from swarm.cli.common import _summary_table as cli_table
    from swarm.studies.report import _summary_table as html_table

    nan = float("nan")
    block = {"self": {"att_rad": 1e-4, "pos_m": 0.01}, "others": {"att_rad": nan, "pos_m": nan}}
    s = {"rms": block, "rms_second_half": block, "nees": {"mean": nan}, "gate": {"accepted": 0, "rejected": 0},
         "interrupted": {"reason": "bus lost", "last_step": 7, "steps_planned": 61}}
    con = Console(width=200, record=True)
    con.print(cli_table(s, "t"))
    text = con.export_text()
    page = html_table(s)
    for out in (text, page):
        assert "nan" not in out.lower(), out
        assert "no data" in out and "bus lost" in out and "step 7 of 60" in out, out


def test_report_of_a_long_range_run_shows_ranges_and_percent_of_range(tmp_path):
    """A long-range run (starfox: km apart, angles only) gets the range figure, whose
    percentages are its relative errors over the true ranges; a close-range run does not."""
    import numpy as np

    from swarm.studies.report import LONG_RANGE_M, load_run

    run = tmp_path / "starfox"
    swarm("sim", "scenarios/starfox.yaml", "--out", str(run), "--set", "duration_s=200", "--no-scene")
    swarm("report", str(run))
    assert (run / "report" / "range.png").is_file()
    assert "<h2>Range</h2>" in (run / "report" / "report.html").read_text()
    data = load_run(run)
    assert data.r_true_H is not None and data.r_true_H.shape == (len(data.t), data.n, 3)
    ranges = np.linalg.norm(data.r_true_H[:, 1:] - data.r_true_H[:, :1], axis=-1)
    assert ranges.min() > LONG_RANGE_M
    close = tmp_path / "demo"
    swarm("sim", "scenarios/demo.yaml", "--out", str(close), "--set", "duration_s=5", "--no-scene")
    swarm("report", str(close))
    assert not (close / "report" / "range.png").exists()
    assert "<h2>Range</h2>" not in (close / "report" / "report.html").read_text()
