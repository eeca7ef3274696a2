"""Independent reference for swarmcore.orbit: two-body + J2 orbits propagated by Basilisk.

Run with a virtualenv that has Basilisk (``pip install bsk``; it is NOT a project
dependency and must not go into the project's .venv)::

    python3 -m venv /work/scratch/bsk-venv && /work/scratch/bsk-venv/bin/pip install bsk
    /work/scratch/bsk-venv/bin/python scripts/basilisk_reference.py tests/data/basilisk_j2_reference.json

It writes a small JSON file that ``tests/test_orbit.py`` reads, so the comparison runs
without Basilisk. Self-contained on purpose (numpy and Basilisk only, nothing from this
project): the initial states are made here from classical elements with Basilisk's own
``orbitalMotion.elem2rv`` and the deputies are placed with a Hill frame written out below,
so a shared mistake in ``swarmcore.orbit`` cannot hide in the reference.

Cases (each a chief and one deputy, both propagated as ordinary spacecraft hubs):

* ``close``: chief at ~550 km altitude, e = 0.001, i = 97.6°, deputy 7–30 m away on a
  near-periodic HCW ellipse;
* ``along_track_50km``: the same chief, deputy 50 km behind it along-track (same orbit,
  shifted in argument of latitude: a pure along-track separation).

Gravity: Earth point mass + degree-2 zonal harmonic only (Basilisk's spherical harmonics
model, degree and order 2, every coefficient but C̄20 zero; C̄20 = −J2/√5 is the fully
normalised coefficient of J2), μ = 3.986004418e14 m³/s², R = 6378137 m, J2 = 1.08262668e-3
(the constants of swarmcore.orbit). No Sun, Moon, drag or SPICE: Earth sits at the origin
with an identity attitude, which for a zonal field is exact whatever its spin.
Integrator: Basilisk's RKF78 (adaptive, tight tolerances) inside a 10 s dynamics task;
output every 60 s over one orbital period.
"""

from __future__ import annotations

import json
import math
import os
import sys
import tempfile

import numpy as np
from Basilisk import __version__ as BSK_VERSION
from Basilisk.simulation import spacecraft, svIntegrators
from Basilisk.utilities import SimulationBaseClass, macros, orbitalMotion, simIncludeGravBody

MU = 3.986004418e14
RE = 6378137.0
J2 = 1.08262668e-3

OUT_STEP_S = 60.0
TASK_STEP_S = 10.0


def hill_T_IH(r, v):
    """Columns: x = r/|r|, z = h/|h|, y = z × x (H → I)."""
    x = r / np.linalg.norm(r)
    h = np.cross(r, v)
    z = h / np.linalg.norm(h)
    return np.column_stack([x, np.cross(z, x), z])


def deputy_from_hill(r_c, v_c, r_H, v_H):
    """Deputy ECI state from its Hill-frame state (two-body frame rate ω = h/r² about z)."""
    T = hill_T_IH(r_c, v_c)
    h = np.linalg.norm(np.cross(r_c, v_c))
    w = np.array([0.0, 0.0, h / np.dot(r_c, r_c)])
    return r_c + T @ r_H, v_c + T @ (v_H + np.cross(w, r_H))


def write_gravity_file(path):
    """A JPL-format spherical harmonics file with only C̄20 (normalised) non-zero."""
    c20 = -J2 / math.sqrt(5.0)
    with open(path, "w") as f:
        f.write(f"{RE!r},{MU!r},0.0,2,2,1,0.0,0.0\n")
        f.write("0,0,1.0,0.0,0.0,0.0\n")
        f.write("1,0,0.0,0.0,0.0,0.0\n1,1,0.0,0.0,0.0,0.0\n")
        f.write(f"2,0,{c20!r},0.0,0.0,0.0\n2,1,0.0,0.0,0.0,0.0\n2,2,0.0,0.0,0.0,0.0\n")


def propagate(states, duration_s, grav_file):
    """Propagate every (r, v) in ``states`` with Basilisk; positions (K, n, 3) and velocities."""
    sim = SimulationBaseClass.SimBaseClass()
    proc = sim.CreateNewProcess("dyn")
    proc.addTask(sim.CreateNewTask("task", macros.sec2nano(TASK_STEP_S)))
    grav = simIncludeGravBody.gravBodyFactory()
    earth = grav.createEarth()
    earth.isCentralBody = True
    earth.mu = MU
    earth.radEquator = RE
    earth.useSphericalHarmonicsGravityModel(grav_file, 2)
    recorders, scs = [], []
    for k, (r, v) in enumerate(states):
        sc = spacecraft.Spacecraft()
        sc.ModelTag = f"sc{k}"
        integ = svIntegrators.svIntegratorRKF78(sc)
        integ.relTol = 1e-13
        integ.absTol = 1e-9
        sc.setIntegrator(integ)
        sc.hub.r_CN_NInit = [float(x) for x in r]
        sc.hub.v_CN_NInit = [float(x) for x in v]
        grav.addBodiesTo(sc)
        sim.AddModelToTask("task", sc)
        rec = sc.scStateOutMsg.recorder(macros.sec2nano(OUT_STEP_S))
        sim.AddModelToTask("task", rec)
        recorders.append(rec)
        scs.append((sc, integ))
    sim.InitializeSimulation()
    sim.ConfigureStopTime(macros.sec2nano(duration_s))
    sim.ExecuteSimulation()
    t = np.array(recorders[0].times()) * 1e-9
    r = np.stack([np.array(rec.r_BN_N) for rec in recorders], axis=1)
    v = np.stack([np.array(rec.v_BN_N) for rec in recorders], axis=1)
    return t, r, v


def main(out_path: str) -> None:
    el = orbitalMotion.ClassicElements()
    el.a = RE + 550e3
    el.e = 0.001
    el.i = math.radians(97.6)
    el.Omega = math.radians(30.0)
    el.omega = math.radians(45.0)
    el.f = math.radians(10.0)
    r_c, v_c = orbitalMotion.elem2rv(MU, el)
    r_c, v_c = np.asarray(r_c, float), np.asarray(v_c, float)
    n = math.sqrt(MU / el.a**3)
    period = 2.0 * math.pi / n
    duration = math.floor(period / OUT_STEP_S) * OUT_STEP_S + OUT_STEP_S  # one orbit, on the grid

    # Close formation: an HCW ellipse (ẏ0 = −2 n x0 keeps it near-periodic), 7–30 m from the chief.
    r_H = np.array([6.0, -16.0, 8.0])
    v_H = np.array([0.001, -2.0 * n * r_H[0], -0.002])
    r_d1, v_d1 = deputy_from_hill(r_c, v_c, r_H, v_H)

    # 50 km along-track: the chief's orbit, the deputy 50 km behind (true anomaly shifted).
    el2 = orbitalMotion.ClassicElements()
    for name in ("a", "e", "i", "Omega", "omega"):
        setattr(el2, name, getattr(el, name))
    el2.f = el.f - 50e3 / el.a
    r_d2, v_d2 = orbitalMotion.elem2rv(MU, el2)
    r_d2, v_d2 = np.asarray(r_d2, float), np.asarray(v_d2, float)

    with tempfile.TemporaryDirectory() as tmp:
        grav_file = os.path.join(tmp, "j2_only.csv")
        write_gravity_file(grav_file)
        t, r, v = propagate([(r_c, v_c), (r_d1, v_d1), (r_d2, v_d2)], duration, grav_file)

    out = {
        "source": f"Basilisk {BSK_VERSION} (pip bsk), scripts/basilisk_reference.py",
        "gravity": "point mass + J2 (spherical harmonics, degree 2, only C20 non-zero), no drag, no third bodies",
        "integrator": "Basilisk svIntegratorRKF78, relTol 1e-13, absTol 1e-9, task 10 s",
        "mu_m3_s2": MU,
        "r_earth_m": RE,
        "j2": J2,
        "chief_elements": {
            "a_m": el.a, "e": el.e, "i_rad": el.i, "raan_rad": el.Omega, "argp_rad": el.omega, "nu_rad": el.f,
        },
        "deputy_50km_nu_rad": el2.f,
        "period_s": period,
        "t_s": t.tolist(),
        "cases": {
            "close": {"deputy_r_H_m": r_H.tolist(), "deputy_v_H_m_s": v_H.tolist(), "sat_index": [0, 1]},
            "along_track_50km": {"sat_index": [0, 2]},
        },
        "r0_I_m": [r_c.tolist(), r_d1.tolist(), r_d2.tolist()],
        "v0_I_m_s": [v_c.tolist(), v_d1.tolist(), v_d2.tolist()],
        "r_I_m": r.tolist(),
        "v_I_m_s": v.tolist(),
    }
    with open(out_path, "w") as f:
        json.dump(out, f, indent=None, separators=(",", ":"))
        f.write("\n")
    sep = np.linalg.norm(r[:, 1] - r[:, 0], axis=1)
    print(f"wrote {out_path}: {len(t)} samples over {t[-1]:.0f} s; close separation {sep.min():.1f}..{sep.max():.1f} m")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "tests/data/basilisk_j2_reference.json")
