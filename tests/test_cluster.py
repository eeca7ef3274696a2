"""Studies on a Dask cluster and on the local pool: same numbers, lost workers, failed runs,
interrupted studies resumed.

The cluster tests start a real scheduler and two real worker processes with Dask's own
commands (``python -m dask scheduler`` / ``python -m dask worker``, on 127.0.0.1; see
:class:`swarm.studies.dask_local.LocalDaskProcesses`) and run ``swarm mc`` / ``swarm compare`` /
``swarm characterize`` as processes against them. Nothing is mocked; every process is
stopped at the end of its test, whatever happens.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from swarm.studies.executor import ResultStore, fingerprint

ROOT = Path(__file__).resolve().parents[1]
SWARM = [sys.executable, "-m", "swarm.cli"]
DEMO = ["scenarios/demo.yaml"]


ENV = dict(os.environ, COLUMNS="250")  # rich wraps its output at the terminal width


def swarm(*args, check=True, timeout=600, env=None):
    p = subprocess.run([*SWARM, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout, env={**ENV, **(env or {})})
    if check and p.returncode != 0:
        raise AssertionError(f"swarm {' '.join(args)} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
    return p


def _no_timing(summary: dict) -> dict:
    """A run summary without its wall-clock and CPU-time fields (the only ones that may differ)."""
    return {k: v for k, v in summary.items() if k not in ("timing", "cpu")}


def _mc_numbers(out: Path) -> dict:
    """Everything in an MC folder that must not depend on where the runs ran."""
    mc = json.loads((out / "mc.json").read_text())
    runs = {p.name: _no_timing(json.loads((p / "summary.json").read_text())) for p in sorted(out.glob("run_*"))}
    stats = {k: v for k, v in mc["stats"].items() if not k.startswith(("timing.", "cpu."))}
    return {"seeds": mc["seeds"], "per_run": mc["per_run"], "stats": stats, "failed": mc["failed"], "runs": runs}


def _lines(path: Path) -> list[dict]:
    return [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []


def _wait_until(pred, timeout: float, what: str) -> None:
    """Wait for a condition on files another process writes (checked every 50 ms)."""
    ev = threading.Event()
    for _ in range(int(timeout / 0.05)):
        if pred():
            return
        ev.wait(0.05)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


# --- the local pool (no Dask process) ---------------------------------------------------


def test_store_drops_a_torn_last_line_and_matches_by_fingerprint(tmp_path):
    def task(a, b):
        return a + b

    p = tmp_path / "results.jsonl"
    s = ResultStore(p)
    s.add("1", fingerprint(task, (1, 2)), 3)
    s.add("2", fingerprint(task, (2, 2)), 4)
    s.close()
    with open(p, "a") as f:
        f.write('{"key": "3", "fp": "abc", "res')  # killed mid-write
    s = ResultStore(p, resume=True)
    assert s.get("1", fingerprint(task, (1, 2))) == (True, 3)
    assert s.get("2", fingerprint(task, (2, 3))) == (False, None)  # other arguments: not reused
    assert s.get("3", "abc") == (False, None)
    s.add("3", fingerprint(task, (3, 2)), 5)
    s.close()
    assert [r["key"] for r in _lines(p)] == ["1", "2", "3"]  # the torn line is gone, the file parses
    s = ResultStore(p)  # without resume: afresh
    assert s.discarded == 3 and s.stored == {}
    s.close()
    assert p.read_text() == ""


def test_local_mc_reports_failed_seeds_and_resumes_without_redoing_runs(tmp_path):
    """Seeds −1…2: run −1 fails validation (seed must be ≥ 0) and is reported by seed with
    its error; the others complete; the exit status is 1. --resume then skips the three
    finished runs (their files untouched) and retries only the failed one."""
    out = tmp_path / "mc"
    args = ["mc", *DEMO, "--runs", "4", "--seed", "-1", "--workers", "2", "--out", str(out), "--set", "duration_s=6"]
    p = swarm(*args, check=False)
    assert p.returncode == 1, p.stderr
    mc = json.loads((out / "mc.json").read_text())
    assert mc["runs_ok"] == 3 and [r["seed"] for r in mc["per_run"]] == [0, 1, 2]
    assert [f["seed"] for f in mc["failed"]] == [-1] and "seed" in mc["failed"][0]["error"]
    assert "greater than or equal to 0" in mc["failed"][0]["error"]
    assert "failed runs: 1" in p.stderr and "-1" in p.stderr
    assert sorted(r["key"] for r in _lines(out / "results.jsonl")) == ["0", "1", "2"]
    stamps = {d.name: (d / "summary.json").stat().st_mtime_ns for d in out.glob("run_*")}
    p2 = swarm(*args, "--resume", check=False)
    assert p2.returncode == 1
    assert "resume: 3 of 4 runs already done" in p2.stderr and "1 runs on" in p2.stderr
    assert {d.name: (d / "summary.json").stat().st_mtime_ns for d in out.glob("run_*")} == stamps
    assert len(_lines(out / "results.jsonl")) == 3  # nothing ran twice
    assert json.loads((out / "mc.json").read_text())["per_run"] == mc["per_run"]
    # Another scenario value: stored runs do not match it, so all of them run again.
    p3 = swarm(*args[:-1], "duration_s=7", "--resume", check=False)
    assert "resume:" not in p3.stderr and "4 runs on" in p3.stderr


@pytest.mark.integration
def test_pool_processes_die_with_a_killed_study(tmp_path):
    """SIGKILL `swarm mc` while its pool runs: the pool's processes end too."""
    import psutil

    out = tmp_path / "mc"
    study = subprocess.Popen([*SWARM, "mc", *DEMO, "--runs", "40", "--workers", "2", "--out", str(out),
                              "--set", "duration_s=30"], cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        _wait_until(lambda: len(_lines(out / "results.jsonl")) >= 1, 300, "a first finished run")
        children = psutil.Process(study.pid).children(recursive=True)
        assert len([c for c in children if "spawn_main" in " ".join(c.cmdline())]) == 2
    finally:
        study.send_signal(signal.SIGKILL)
        study.wait()
    _gone, alive = psutil.wait_procs(children, timeout=30)
    assert not alive, f"orphaned pool processes: {alive}"


@pytest.mark.integration
def test_unreachable_cluster_is_a_clear_error(tmp_path):
    from swarm.supervise.launch import free_port

    p = swarm("mc", *DEMO, "--runs", "1", "--out", str(tmp_path / "x"), "--cluster", f"tcp://127.0.0.1:{free_port()}",
              "--set", "duration_s=2", check=False, timeout=120)
    assert p.returncode == 2
    assert "cannot reach the Dask scheduler" in p.stderr


# --- a real Dask cluster: scheduler + two workers as processes ---------------------------


@pytest.fixture
def cluster(tmp_path):
    pytest.importorskip("distributed")
    from swarm.studies.dask_local import LocalDaskProcesses

    c = LocalDaskProcesses(2, workdir=tmp_path / "dask")
    c.start()
    try:
        yield c
    finally:
        c.stop()
    assert all(p.poll() is not None for p in [c.scheduler, *c.workers.values()])


@pytest.mark.integration
def test_cluster_mc_gives_the_local_pools_numbers(cluster, tmp_path):
    sets = ["--set", "duration_s=10"]
    local, remote = tmp_path / "local", tmp_path / "cluster"
    swarm("mc", *DEMO, "--runs", "4", "--seed", "7", "--workers", "2", "--out", str(local), *sets)
    p = swarm("mc", *DEMO, "--runs", "4", "--seed", "7", "--cluster", cluster.address, "--out", str(remote), *sets,
              env={"SWARM_PROGRESS": "1"})  # the progress bar, drawn even without a terminal
    assert f"on Dask scheduler {cluster.address} (2 workers, 2 threads)" in p.stderr
    assert "mc demo ×4" in p.stderr and "4/4" in p.stderr
    assert json.loads((remote / "mc.json").read_text())["backend"].startswith("Dask scheduler")
    a, b = _mc_numbers(local), _mc_numbers(remote)
    assert a["seeds"] == [7, 8, 9, 10] and len(a["runs"]) == 4
    assert a == b  # bit for bit, every field but wall-clock timings


@pytest.mark.integration
@pytest.mark.slow
def test_workers_started_by_hand_from_a_clean_environment_give_the_local_pools_numbers(tmp_path):
    """Workers started as docs/deployment.md says, from an environment that knows nothing of the
    project (no OPENBLAS_*): with the project's nanny preload they compute the local pool's
    numbers bit for bit; without it, on a CPU whose OpenBLAS would pick other kernels, every
    task is refused with a message naming the preload (never numbers 1e-7 off)."""
    from swarm.studies.dask_local import LocalDaskProcesses

    clean = {"PATH": os.environ["PATH"], "HOME": os.environ.get("HOME", "/root"), "LANG": "C.UTF-8"}
    args = ["mc", "scenarios/baseline.yaml", "--runs", "2", "--seed", "77", "--set", "n_sats=4", "--set", "duration_s=20"]
    local = tmp_path / "local"
    swarm(*args, "--workers", "1", "--out", str(local))
    with LocalDaskProcesses(1, workdir=tmp_path / "dask-pre", env=clean, nanny=True,
                            worker_args=("--preload-nanny", "swarm.studies.dask_preload")) as c:
        swarm(*args, "--cluster", c.address, "--out", str(tmp_path / "pre"))
    assert _mc_numbers(local) == _mc_numbers(tmp_path / "pre")
    with LocalDaskProcesses(1, workdir=tmp_path / "dask-bare", env=clean, nanny=True) as c:
        p = swarm(*args, "--cluster", c.address, "--out", str(tmp_path / "bare"), check=False)
    if p.returncode == 0:  # this CPU's OpenBLAS picks the pinned kernels anyway
        assert _mc_numbers(local) == _mc_numbers(tmp_path / "bare")
    else:
        assert p.returncode == 1
        text = " ".join((p.stdout + p.stderr).split())
        assert "--preload-nanny swarm.studies.dask_preload" in text or "NumbersEnvironmentError" in text, text[-2000:]
        assert not (tmp_path / "bare" / "run_0000" / "summary.json").exists()


@pytest.mark.integration
def test_cluster_links_study_gives_the_local_pools_numbers(cluster, tmp_path):
    scen = ["scenarios/links-study.yaml", "--runs", "1", "--latencies", "0,2", "--losses", "0.3", "--caps", "",
            "--set", "duration_s=6", "--set", "n_sats=4"]
    local, remote = tmp_path / "local", tmp_path / "cluster"
    swarm("links-study", *scen, "--workers", "2", "--out", str(local))
    swarm("links-study", *scen, "--cluster", cluster.address, "--out", str(remote))

    def cells(out):
        doc = json.loads((out / "links_study.json").read_text())
        return {c["key"]: [{k: v for k, v in r.items() if k != "wall_s"} for r in c["runs"]] for c in doc["cells"]}

    a, b = cells(local), cells(remote)
    assert len(a) == 6 and a == b


@pytest.mark.integration
def test_cluster_compare_gives_the_local_pools_numbers(cluster, tmp_path):
    args = ["compare", "scenarios/selection.yaml", "--runs", "2", "--strategies", "random,greedy", "--set", "duration_s=6",
            "--set", "n_sats=5", "--set", "selection.budget=3"]
    swarm(*args, "--workers", "2", "--out", str(tmp_path / "local"))
    swarm(*args, "--cluster", cluster.address, "--out", str(tmp_path / "cluster"))

    def numbers(out):
        doc = json.loads((out / "compare.json").read_text())
        wall = ("wall_s", "select_ms_median", "select_ms_mean")
        return doc["seeds"], {s: [{k: v for k, v in r.items() if k not in wall} for r in rows] for s, rows in doc["per_run"].items()}

    assert numbers(tmp_path / "local") == numbers(tmp_path / "cluster")


@pytest.mark.integration
@pytest.mark.slow
def test_a_worker_killed_mid_run_costs_only_its_task(cluster, tmp_path):
    """SIGKILL worker w0 the moment a run starts executing on it (a worker plugin reports
    the start; no guessing with delays): the scheduler runs that task again on w1, the study
    completes with every seed, and the numbers are those of the same seeds in-process."""
    from distributed import Client

    from swarm.simulation import simulate_scenario
    from swarm.studies.dask_local import TASK_TOPIC, TaskEvents, parse_key
    from swarmrt.scenario_files import load_scenario

    events: list[dict] = []
    started_on_w0 = threading.Event()

    def on_event(ev):
        msg = ev[1]
        events.append(msg)
        if msg["name"] == "w0" and msg["state"] == "executing" and parse_key(msg["key"])[0] == "mc.run_one":
            started_on_w0.set()

    out = tmp_path / "mc"
    runs, sets = 6, ["--set", "duration_s=120"]
    with Client(cluster.address, timeout=30, set_as_default=False) as watch:
        watch.register_plugin(TaskEvents())
        watch.subscribe_topic(TASK_TOPIC, on_event)
        study = subprocess.Popen([*SWARM, "mc", *DEMO, "--runs", str(runs), "--seed", "3", "--cluster", cluster.address,
                                  "--out", str(out), *sets], cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert started_on_w0.wait(180), "no run ever started on w0"
            victim = next(m["key"] for m in events if m["name"] == "w0" and m["state"] == "executing"
                          and parse_key(m["key"])[0] == "mc.run_one")
            cluster.kill_worker("w0")
            _stdout, stderr = study.communicate(timeout=600)
        finally:
            if study.poll() is None:
                study.kill()
                study.wait()
        assert cluster.workers["w0"].returncode == -signal.SIGKILL
        assert study.returncode == 0, stderr
        # The killed run was not finished on w0; w1 ran it again.
        assert not any(m["key"] == victim and m["name"] == "w0" and m["state"] != "executing" for m in events)
        assert any(m["key"] == victim and m["name"] == "w1" and m["state"] == "executing" for m in events)
    mc = json.loads((out / "mc.json").read_text())
    assert mc["runs_ok"] == runs and mc["failed"] == [] and [r["seed"] for r in mc["per_run"]] == list(range(3, 3 + runs))
    for i, seed in enumerate(mc["seeds"]):
        # what `swarm sim` computes (the radio's bytes included)
        ref = simulate_scenario(load_scenario(ROOT / "scenarios/demo.yaml", ["duration_s=120"], seed=seed)).summary()
        got = json.loads((out / f"run_{i:04d}" / "summary.json").read_text())
        assert _no_timing(got) == _no_timing(json.loads(json.dumps(ref))), f"seed {seed}"


@pytest.mark.integration
@pytest.mark.slow
def test_an_interrupted_cluster_study_resumes_without_redoing_finished_runs(cluster, tmp_path):
    """Kill the study (SIGKILL of `swarm mc`) once 3 of 8 runs are on disk; run the same
    command with --resume: it says it skipped them, and the workers start exactly the runs
    that were not finished (counted from the workers' own task events), each once."""
    from distributed import Client

    from swarm.studies.dask_local import TASK_TOPIC, TaskEvents, parse_key, scheduler_task_count

    out = tmp_path / "mc"
    args = ["mc", *DEMO, "--runs", "8", "--seed", "20", "--cluster", cluster.address, "--out", str(out), "--set", "duration_s=40"]
    first = subprocess.Popen([*SWARM, *args], cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        _wait_until(lambda: len(_lines(out / "results.jsonl")) >= 3, 300, "3 finished runs")
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait()
    done = {r["key"] for r in _lines(out / "results.jsonl")}
    assert 3 <= len(done) < 8, "the study finished before it could be interrupted"
    assert not (out / "mc.json").exists()
    started: list[str] = []
    with Client(cluster.address, timeout=30, set_as_default=False) as watch:
        # the scheduler has dropped the killed study's tasks: none of them starts any more
        _wait_until(lambda: watch.run_on_scheduler(scheduler_task_count) == 0, 60, "the killed study's tasks to go")
        watch.register_plugin(TaskEvents())
        watch.subscribe_topic(TASK_TOPIC, lambda ev: ev[1]["state"] == "executing" and started.append(ev[1]["key"]))
        p = swarm(*args, "--resume")
        # the scheduler forwards the last events within milliseconds; they are in by the time
        # the study has its results, but wait for the count rather than assume it
        todo = {str(s) for s in range(20, 28)} - done
        _wait_until(lambda: {parse_key(k)[1] for k in started if parse_key(k)[0] == "mc.run_one"} >= todo, 30, "events")
    assert f"resume: {len(done)} of 8 runs already done" in p.stderr
    ran = [parse_key(k)[1] for k in started if parse_key(k)[0] == "mc.run_one"]
    assert sorted(ran) == sorted(todo)  # exactly the unfinished runs, each once
    mc = json.loads((out / "mc.json").read_text())
    assert mc["runs_ok"] == 8 and mc["skipped"] == len(done) and mc["failed"] == []
    assert sorted(r["key"] for r in _lines(out / "results.jsonl")) == sorted(str(s) for s in range(20, 28))


@pytest.mark.integration
@pytest.mark.render
@pytest.mark.slow
def test_cluster_characterize_gives_the_same_samples_as_in_process(cluster, tmp_path):
    args = ["characterize", "--pipeline", "mono", "--ranges", "3,6", "--orientations", "1", "--suns", "2",
            "--illumination", "global"]
    swarm(*args, "--out", str(tmp_path / "here"))
    p = swarm(*args, "--out", str(tmp_path / "cluster"), "--cluster", cluster.address)
    assert "2 cells on Dask scheduler" in p.stderr

    def samples(d):
        (f,) = d.glob("characterization-*.json")
        return json.loads(f.read_text())["samples"]

    a, b = samples(tmp_path / "here"), samples(tmp_path / "cluster")
    assert len(a) == 4 and a == b


# --- the compose profile: scheduler and workers in containers of the project's image -----


@pytest.fixture(scope="module")
def cluster_image() -> str:
    """The project's image, built or refreshed (scripts/docker-build.sh: a no-op when it is
    current). A fixture, so that a cold build is not timed as the test (func_only below)."""
    import shutil

    if shutil.which("docker") is None or subprocess.run(["docker", "info"], capture_output=True).returncode != 0:
        pytest.skip("no docker daemon")
    b = subprocess.run([str(ROOT / "scripts" / "docker-build.sh")], capture_output=True, text=True, timeout=3600)
    assert b.returncode == 0, b.stdout[-3000:] + b.stderr[-3000:]
    return "swarm-coloc:latest"


@pytest.mark.docker
@pytest.mark.integration
@pytest.mark.timeout(600, func_only=True)  # a cold image build (~10 min) is the fixture's, bounded by its own timeout
def test_compose_cluster_profile_runs_a_study(tmp_path, cluster_image):
    """`docker compose --profile cluster up -d dask-scheduler dask-worker`: a scheduler and
    two workers from swarm-coloc:latest; a tiny MC from the host against it gives the local
    pool's numbers; the default services are not started, the keys service neither (the
    cluster needs no keys: none are made)."""
    import uuid

    from swarm.chaos.compose import compose_command
    from swarm.studies.executor import connect
    from swarm.supervise.launch import free_port

    try:
        compose = compose_command()
    except RuntimeError as exc:
        pytest.skip(str(exc))
    port = free_port()
    project = f"swc{uuid.uuid4().hex[:8]}"
    keys = tmp_path / "keys"  # does not exist, and must not after
    env = dict(os.environ, SWARM_DASK_PORT=str(port), SWARM_DASK_WORKERS="2", COMPOSE_PROJECT_NAME=project, SWARM_KEYS=str(keys))
    dc = [*compose, "-f", str(ROOT / "compose.yaml"), "-p", project]

    def run(*args, timeout=600):
        p = subprocess.run([*dc, *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
        assert p.returncode == 0, f"{' '.join(args)}: {p.stdout[-2000:]}\n{p.stderr[-2000:]}"
        return p

    try:
        run("--profile", "cluster", "up", "-d", "dask-scheduler", "dask-worker")
        with connect(f"tcp://127.0.0.1:{port}", 120) as c:  # retries while the container starts
            c.wait_for_workers(2, timeout=180)
        running = run("ps", "--services", "--filter", "status=running").stdout.split()
        assert sorted(running) == ["dask-scheduler", "dask-worker"]
        assert not keys.exists()
        sets = ["--set", "duration_s=8"]
        swarm("mc", *DEMO, "--runs", "3", "--seed", "11", "--out", str(tmp_path / "local"), *sets)
        p = swarm("mc", *DEMO, "--runs", "3", "--seed", "11", "--out", str(tmp_path / "cluster"), *sets,
                  "--cluster", f"tcp://127.0.0.1:{port}")
        assert "(2 workers, 2 threads)" in p.stderr
    finally:
        subprocess.run([*dc, "--profile", "cluster", "down", "-v", "--remove-orphans", "-t", "5"], cwd=ROOT, env=env,
                       capture_output=True, timeout=300)
    assert _mc_numbers(tmp_path / "local") == _mc_numbers(tmp_path / "cluster")  # containers = host, bit for bit
