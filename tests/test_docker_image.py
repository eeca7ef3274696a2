"""The swarm-coloc container image: it builds, runs every role's entry point,
renders headless, and simulates bit for bit what the host simulates.

Builds (or refreshes) the image with scripts/docker-build.sh first: a no-op
when nothing changed, about a minute after a code change, several minutes from
nothing (base image, wheelhouse, dependencies). Skipped only when Docker itself
is not usable here.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
IMAGE = os.environ.get("SWARM_IMAGE", "swarm-coloc:latest")
BUILD_TIMEOUT_S = 3000

pytestmark = [pytest.mark.docker, pytest.mark.timeout(BUILD_TIMEOUT_S + 600)]


def _docker_problem() -> str | None:
    if shutil.which("docker") is None:
        return "docker CLI not installed"
    try:
        r = subprocess.run(["docker", "info", "--format", "{{.ServerVersion}}"],
                           capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"docker info failed: {exc}"
    if r.returncode != 0:
        return f"docker daemon not reachable: {(r.stderr or r.stdout).strip()[:200]}"
    return None


@pytest.fixture(scope="module")
def image() -> str:
    problem = _docker_problem()
    if problem:
        pytest.skip(f"Docker not available: {problem}")
    # Always run the build script: it does nothing when the image is current,
    # and the host/container comparison below needs the current source in it.
    # The script takes a machine-wide lock, so xdist workers build one at a time.
    if os.environ.get("SWARM_DOCKER_NO_BUILD") != "1":
        r = subprocess.run(["bash", str(ROOT / "scripts" / "docker-build.sh")], cwd=ROOT,
                           capture_output=True, text=True, timeout=BUILD_TIMEOUT_S,
                           env=dict(os.environ, IMAGE=IMAGE))
        assert r.returncode == 0, f"scripts/docker-build.sh failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    r = subprocess.run(["docker", "image", "inspect", IMAGE], capture_output=True, text=True)
    assert r.returncode == 0, f"image {IMAGE} missing after the build"
    return IMAGE


def docker_run(image: str, *args: str, volumes: dict[Path, str] | None = None,
               timeout: float = 300) -> subprocess.CompletedProcess:
    cmd = ["docker", "run", "--rm", "--user", f"{os.getuid()}:{os.getgid()}", "-e", "HOME=/tmp"]
    # The host's BLAS kernel family (pinned by swarmcore, or the user's), as compose passes it.
    cmd += ["-e", f"OPENBLAS_CORETYPE={os.environ.get('OPENBLAS_CORETYPE', '')}"]
    for host, inside in (volumes or {}).items():
        cmd += ["-v", f"{host}:{inside}"]
    return subprocess.run([*cmd, image, *args], capture_output=True, text=True, timeout=timeout)


def test_help(image):
    r = docker_run(image, "swarm", "--help")
    assert r.returncode == 0, r.stderr
    assert "sim" in r.stdout and "Usage" in r.stdout


def test_default_command_is_help(image):
    r = docker_run(image)
    assert r.returncode == 0, r.stderr
    assert "Usage" in r.stdout


def test_image_env(image):
    r = docker_run(image, "env")
    assert r.returncode == 0, r.stderr
    env = dict(line.split("=", 1) for line in r.stdout.splitlines() if "=" in line)
    assert env.get("PYOPENGL_PLATFORM") == "egl"
    assert env.get("OPENBLAS_NUM_THREADS") == "1"


@pytest.mark.parametrize("role", ["world_sim", "sat_agent", "selector", "swarm.record.recorder", "swarm.supervise.router"])
def test_role_modules_start(image, role):
    """`docker run IMAGE <module> ...` runs `python -m <module> ...` (docker/entrypoint.sh)."""
    r = docker_run(image, role, "--help")
    assert r.returncode == 0, f"{role}: {r.stderr[-2000:]}"
    assert "usage" in r.stdout.lower()


def test_image_carries_traffic_control(image):
    """`swarm fault --compose netem` runs tc (iproute2) and, on kernels without netem,
    iptables and `python -m swarm.supervise.netemd` in a helper container of this image."""
    r = docker_run(image, "sh", "-c", "tc -V && iptables --version && ip -V && python -m swarm.supervise.netemd --help")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "iproute2" in r.stdout and "iptables v" in r.stdout and "NFQUEUE" in r.stdout, r.stdout


@pytest.mark.render
@pytest.mark.parametrize("platform", ["egl", "osmesa"])
def test_headless_render_in_container(image, platform):
    code = (
        "import numpy as np\n"
        "np.infty = np.inf  # pyrender 0.1.45 on NumPy 2\n"
        "import pyrender, trimesh\n"
        "s = pyrender.Scene(bg_color=[0, 0, 0, 0])\n"
        "s.add(pyrender.Mesh.from_trimesh(trimesh.creation.box((1, 1, 1)), smooth=False))\n"
        "pose = np.eye(4); pose[2, 3] = 3.0\n"
        "s.add(pyrender.IntrinsicsCamera(80, 80, 32, 24), pose=pose)\n"
        "s.add(pyrender.DirectionalLight(intensity=3.0), pose=pose)\n"
        "r = pyrender.OffscreenRenderer(64, 48)\n"
        "color, depth = r.render(s)\n"
        "r.delete()\n"
        "assert color.shape == (48, 64, 3) and depth[24, 32] > 0, depth[24, 32]\n"
        "print('depth', depth[24, 32])\n"
    )
    r = docker_run(image, "env", f"PYOPENGL_PLATFORM={platform}", "python", "-c", code)
    assert r.returncode == 0, r.stderr[-3000:]
    assert abs(float(r.stdout.split()[-1]) - 2.5) < 1e-3  # box face at z = 3 - 0.5


def _host_swarm() -> list[str]:
    exe = Path(sys.executable).with_name("swarm")
    if exe.exists():
        return [str(exe)]
    found = shutil.which("swarm")
    assert found, "the swarm command is not installed on the host"
    return [found]


def _walk(a, b, path=""):
    """Pairs of differing leaves of two JSON trees (exact comparison)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = [(f"{path}.{k}", "missing", "present") for k in b.keys() - a.keys()]
        out += [(f"{path}.{k}", "present", "missing") for k in a.keys() - b.keys()]
        for k in a.keys() & b.keys():
            out += _walk(a[k], b[k], f"{path}.{k}")
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in _walk(x, y, f"{path}[{i}]")]
    return [] if a == b else [(path, a, b)]


# Wall-clock measurements: the only outputs allowed to differ between runs.
WALL_CLOCK_SUMMARY_KEYS = {"timing", "cpu"}
WALL_CLOCK_ARRAYS = {"step_ms"}


def test_sim_in_container_matches_host(image, tmp_path):
    """Same scenario and seed: the container's run equals the host's bit for bit.

    Determinism across machines and containers is a product requirement: the
    numbers (summary and every array) must not depend on where the run happens.
    Only wall-clock timings are left out.
    """
    out_c = tmp_path / "container"
    out_c.mkdir()
    r = docker_run(image, "swarm", "sim", "scenarios/demo.yaml", "--out", "/out",
                   volumes={out_c: "/out"}, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    summary_c = json.loads((out_c / "summary.json").read_text())
    assert summary_c["n_sats"] == 4

    out_h = tmp_path / "host"
    r = subprocess.run([*_host_swarm(), "sim", str(ROOT / "scenarios" / "demo.yaml"), "--out", str(out_h)],
                       cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    summary_h = json.loads((out_h / "summary.json").read_text())

    for k in WALL_CLOCK_SUMMARY_KEYS:
        summary_c.pop(k, None)
        summary_h.pop(k, None)
    diffs = _walk(summary_h, summary_c)
    assert not diffs, "host and container summaries differ (path, host, container):\n" + "\n".join(
        f"  {p}: {a!r} vs {b!r}" for p, a, b in diffs[:20])
    assert summary_h["rms"] == summary_c["rms"]  # the headline numbers, exactly

    for name in ("truth.npz", "estimates.npz"):
        if not (out_h / name).exists():
            continue
        with np.load(out_h / name) as h, np.load(out_c / name) as c:
            assert sorted(h.files) == sorted(c.files), name
            for k in h.files:
                if k in WALL_CLOCK_ARRAYS:
                    continue
                assert h[k].dtype == c[k].dtype and h[k].shape == c[k].shape, f"{name}:{k}"
                assert np.array_equal(h[k], c[k], equal_nan=h[k].dtype.kind in "fc"), (
                    f"{name}:{k} differs, max |Δ| = {np.nanmax(np.abs(h[k] - c[k]))}")
