"""The Python API of swarm-coloc: everything the ``swarm`` command does, from Python.

>>> import swarm
>>> sc = swarm.load_scenario("scenarios/demo.yaml", duration_s=20)
>>> res = swarm.simulate(sc)                        # every filter in this process
>>> res.errors.head()                               # a pandas DataFrame
>>> res.plot_errors(filter=0, sat=1)                # errors against ±3σ
>>> cmp = swarm.compare(sc, estimators=["full", "ci"], runs=3)
>>> cmp.summary

* :func:`load_scenario` — a scenario from a YAML file, a dict or the defaults, with overrides;
* :func:`simulate` — in-process (``swarm sim``), returns a :class:`Result`;
* :func:`run` — distributed (``swarm run``: real processes on a local bus), the same
  :class:`Result`, read from the recording;
* :func:`monte_carlo` — runs over seeds (``swarm mc``), a :class:`MonteCarlo`;
* :func:`compare` — paired runs of variants of a scenario (selection strategies as ``swarm
  compare``, estimators, any overrides), a :class:`Comparison`.

A :class:`Result` holds the run's summary (the ``summary.json`` contract) and its arrays as
pandas DataFrames: :attr:`~Result.errors`, :attr:`~Result.covariances`, :attr:`~Result.nees`,
:attr:`~Result.links`, :attr:`~Result.link_latencies` and :attr:`~Result.faults`, one row per
step, filter and satellite (or per step, link, fault). Every name in ``__all__`` is stable;
anything else here may change.

``import swarm`` loads none of this until a name is used (this module and numpy, pandas and
the core then), but it first applies the process's numeric settings
(:func:`swarmrt.tuning.tune_process`), so a notebook computes the same bits as the CLI.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from swarmcore.scenario import Scenario

if TYPE_CHECKING:
    import pandas as pd
    from matplotlib.figure import Figure

    from swarm.supervise.outcome import RunOutcome
    from swarmcore.result import RunResult

__all__ = ["Scenario", "Result", "MonteCarlo", "Comparison", "load_scenario", "simulate", "run", "monte_carlo", "compare"]

Progress = Callable[[int, int], None]
_AXES = ("x", "y", "z")


# -- scenarios ----------------------------------------------------------------------------------
def load_scenario(source: Scenario | str | Path | Mapping[str, Any] | None = None, *, seed: int | None = None,
                  overrides: Mapping[str, Any] | Iterable[str] = (), **fields: Any) -> Scenario:
    """A validated scenario.

    ``source``: a YAML file (``"scenarios/demo.yaml"``), a mapping of fields, a
    :class:`Scenario` (copied) or None (the defaults). ``overrides``: dotted keys, as a
    mapping (``{"estimator.kind": "ci"}``) or ``--set`` strings (``["n_sats=6"]``); keyword
    ``fields`` are top-level ones (``n_sats=6, duration_s=30``). Raises
    :class:`swarmrt.scenario_files.ScenarioError` (a ValueError) naming the field."""
    from swarmrt.scenario_files import ScenarioError, apply_overrides, parse_overrides, scenario_from_dict
    from swarmrt.scenario_files import load_scenario as _load_file

    if isinstance(overrides, Mapping):
        pairs = [(str(k).split("."), v) for k, v in overrides.items()]
    else:
        pairs = parse_overrides(list(overrides))
    pairs += [([k], v) for k, v in fields.items()]
    if source is None or isinstance(source, (str, Path)):
        sc = _load_file(source, (), None)
        data, where = sc.model_dump(mode="json"), str(source or "defaults")
    elif isinstance(source, Scenario):
        data, where = source.model_dump(mode="json"), source.name
    elif isinstance(source, Mapping):
        data, where = dict(source), "scenario"
    else:
        raise ScenarioError(f"load_scenario: expected a file, a mapping or a Scenario, got {type(source).__name__}")
    data = apply_overrides(data, pairs)
    if seed is not None:
        data["seed"] = seed
    return scenario_from_dict(data, where)


def _scenario(scenario, seed: int | None = None, overrides: Mapping[str, Any] | None = None) -> Scenario:
    if isinstance(scenario, Scenario) and seed is None and not overrides:
        return scenario
    return load_scenario(scenario, seed=seed, overrides=overrides or {})


# -- results ------------------------------------------------------------------------------------
class Result:
    """One run: its summary and arrays, from the simulator (:func:`simulate`) or a recording
    (:func:`run`, :meth:`load`). Arrays are (K steps, F filters, n satellites, ...); NaN where
    a filter has no estimate of a satellite (it does not track it, or was dead)."""

    def __init__(self, scenario: Scenario, summary: dict, source: str, path: Path | None = None, *, sim: RunResult | None = None,
                 recording: str | Path | None = None, outcome: RunOutcome | None = None):
        self.scenario = scenario
        self.summary = summary
        self.source = source  # "simulate" | "run" | "folder"
        self.path = path
        self.sim = sim  # the simulator's result (simulate only)
        self.outcome = outcome  # a distributed run's end (run only): exit_code, signal, broken
        self._recording_path = Path(recording) if recording is not None else None
        self._data: RunResult | None = sim
        self._frames: dict[str, pd.DataFrame] = {}

    def __repr__(self) -> str:
        return (f"Result({self.source} of {self.scenario.name!r}: n={self.scenario.n_sats}, {self.summary.get('steps')} steps, "
                f"estimator {self.summary.get('estimator', 'full')}, seed {self.scenario.seed}"
                + (f", {self.path}" if self.path else "") + ")")

    # -- loading ------------------------------------------------------------------------------
    @classmethod
    def load(cls, folder: str | Path) -> Result:
        """A run folder: ``swarm sim``'s (``summary.json``, ``estimates.npz``, ``truth.npz``) or
        ``swarm run``'s (``run.mcap``)."""
        from swarm.outputs import read_json, read_run

        folder = Path(folder)
        sc = load_scenario(folder / "scenario.yaml")
        summary = read_json(folder / "summary.json") if (folder / "summary.json").exists() else {}
        if (folder / "run.mcap").exists():
            return cls(sc, summary, "folder", folder, recording=folder / "run.mcap")
        if not (folder / "estimates.npz").exists():
            raise FileNotFoundError(f"{folder}: neither run.mcap nor estimates.npz (swarm sim --no-arrays keeps no arrays)")
        res = cls(sc, summary, "folder", folder)
        res._data = read_run(folder, sc)
        return res

    @property
    def recording(self) -> RunResult | None:
        """The recording of a distributed run, read (:func:`swarm.record.recording.load_recording`)."""
        if self._recording_path is None:
            return None
        if self._data is None:
            from swarm.record.recording import load_recording

            steps = None if self.summary.get("interrupted") else self.scenario.steps
            self._data = load_recording(self._recording_path, self.scenario.n_sats, steps, scenario=self.scenario)
        return self._data

    @property
    def data(self) -> RunResult:
        """The run's :class:`~swarmcore.result.RunResult` (one schema, whatever ran it): the
        simulator's, the recording's or a run folder's."""
        data = self._data if self._data is not None else self.recording
        if data is None:
            raise ValueError("this result has no arrays")
        return data

    def arrays(self) -> dict[str, Any]:
        """The run's arrays: ``t`` (K,), ``truth_q`` (K, n, 4), ``truth_r`` (K, n, 3),
        ``est_q`` (K, F, n, 4), ``est_r`` (K, F, n, 3), ``pose_var`` (K, F, n, 6: the diagonal
        of each [a, Δr] covariance), ``nees`` (K, F, n), ``link_totals`` (K, 6, cumulative:
        sent, delivered, delivered late, lost, dropped at the queue, unreachable; None without
        links) and ``link_latencies`` (sender, receiver, sent step, latency s)."""
        r = self.data
        return {"t": r.t_s, "truth_q": r.truth.q_BI, "truth_r": r.truth.r_H_m, "est_q": r.est.q_BI, "est_r": r.est.r_H_m,
                "pose_var": r.est.pose_var, "nees": r.nees, "link_totals": r.links.totals if r.links is not None else None,
                "link_latencies": list(r.links.latencies) if r.links is not None else []}

    # -- tables ------------------------------------------------------------------------------------
    def _frame(self, name: str, build: Callable[[], pd.DataFrame]) -> pd.DataFrame:
        if name not in self._frames:
            self._frames[name] = build()
        return self._frames[name]

    def _long(self, values: dict[str, np.ndarray]) -> pd.DataFrame:
        """Rows (k, t_s, filter, sat) where the filter has an estimate of the satellite."""
        import pandas as pd

        a = self.arrays()
        K, F, n = a["est_r"].shape[:3]
        k, f, s = np.meshgrid(np.arange(K), np.arange(F), np.arange(n), indexing="ij")
        keep = np.isfinite(a["est_r"][..., 0]).ravel()
        cols: dict[str, np.ndarray] = {"k": k.ravel()[keep], "t_s": np.broadcast_to(a["t"][:, None, None], (K, F, n)).ravel()[keep],
                                       "filter": f.ravel()[keep], "sat": s.ravel()[keep]}
        for name, v in values.items():
            cols[name] = np.asarray(v).reshape(K * F * n)[keep]
        return pd.DataFrame(cols)

    @property
    def errors(self) -> pd.DataFrame:
        """Each filter's estimation error of each satellite it tracks, per step:
        ``att_err_rad`` (the norm of ``a``, with q = δq(a) ⊗ q̂) and its components
        ``att_err_{x,y,z}_rad`` (body frame); ``pos_err_m`` and ``pos_err_{x,y,z}_m`` (Δr = r −
        r̂, Hill frame); and the 1σ of each component, ``att_sigma_*_rad``, ``pos_sigma_*_m``."""

        def build() -> pd.DataFrame:
            att, dr = self.data.pose_errors()
            sig = np.sqrt(np.clip(self.data.est.pose_var, 0, None))
            cols = {"att_err_rad": np.linalg.norm(att, axis=-1), "pos_err_m": np.linalg.norm(dr, axis=-1)}
            for i, x in enumerate(_AXES):
                cols[f"att_err_{x}_rad"] = att[..., i]
            for i, x in enumerate(_AXES):
                cols[f"pos_err_{x}_m"] = dr[..., i]
            for i, x in enumerate(_AXES):
                cols[f"att_sigma_{x}_rad"] = sig[..., i]
            for i, x in enumerate(_AXES):
                cols[f"pos_sigma_{x}_m"] = sig[..., 3 + i]
            return self._long(cols)

        return self._frame("errors", build)

    @property
    def covariances(self) -> pd.DataFrame:
        """The diagonal of each filter's 6×6 pose covariance of each satellite it tracks:
        ``att_var_{x,y,z}_rad2`` (body frame) and ``pos_var_{x,y,z}_m2`` (Hill frame)."""

        def build() -> pd.DataFrame:
            v = self.arrays()["pose_var"]
            cols = {f"att_var_{x}_rad2": v[..., i] for i, x in enumerate(_AXES)}
            cols |= {f"pos_var_{x}_m2": v[..., 3 + i] for i, x in enumerate(_AXES)}
            return self._long(cols)

        return self._frame("covariances", build)

    @property
    def nees(self) -> pd.DataFrame:
        """Each filter's 6-dof NEES of each satellite it tracks (mean 6 when consistent)."""
        return self._frame("nees", lambda: self._long({"nees": self.arrays()["nees"]}))

    @property
    def links(self) -> pd.DataFrame:
        """What the radio did each step (``links:`` scenarios; empty otherwise): copies
        ``sent``, ``delivered`` (on time or late), ``delivered_late``, ``lost``,
        ``dropped_queue``, ``unreachable`` over all directed links."""

        def build() -> pd.DataFrame:
            import pandas as pd

            a = self.arrays()
            names = ["sent", "delivered", "delivered_late", "lost", "dropped_queue", "unreachable"]
            tot = a["link_totals"]
            if tot is None:
                return pd.DataFrame(columns=["k", "t_s", *names])
            step = np.diff(tot, axis=0, prepend=np.zeros((1, tot.shape[1]), dtype=tot.dtype))
            df = pd.DataFrame(step, columns=names)
            df.insert(0, "t_s", a["t"][: len(df)])
            df.insert(0, "k", np.arange(len(df)))
            return df

        return self._frame("links", build)

    @property
    def link_latencies(self) -> pd.DataFrame:
        """Every delivered batch: ``sender``, ``receiver``, ``sent_k`` and ``latency_s``."""

        def build() -> pd.DataFrame:
            import pandas as pd

            lat = self.arrays()["link_latencies"]
            return pd.DataFrame(np.asarray(lat, dtype=float).reshape(-1, 4), columns=["sender", "receiver", "sent_k", "latency_s"]) \
                .astype({"sender": int, "receiver": int, "sent_k": int})

        return self._frame("link_latencies", build)

    @property
    def faults(self) -> pd.DataFrame:
        """The faults of a distributed run (commands and reports), as in ``summary.json``."""
        import pandas as pd

        return pd.DataFrame(self.summary.get("faults") or [], columns=None)

    @property
    def rms(self) -> pd.DataFrame:
        """The summary's time-RMS errors: rows full run / second half, columns self and others'
        attitude (rad) and position (m)."""
        import pandas as pd

        rows = {}
        for key, label in (("rms", "full run"), ("rms_second_half", "second half")):
            r = self.summary.get(key) or {}
            rows[label] = {f"{w}_{u}": (r.get(w) or {}).get(u, np.nan) for w in ("self", "others") for u in ("att_rad", "pos_m")}
        return pd.DataFrame.from_dict(rows, orient="index")

    # -- saving and plotting ---------------------------------------------------------------------------
    def save(self, out: str | Path, *, arrays: bool = True, extra_summary: dict | None = None) -> dict:
        """Write a ``swarm sim`` folder (summary.json, scenario.yaml and, with ``arrays``,
        truth.npz and estimates.npz) of a simulated result; returns the summary."""
        from swarm.outputs import write_run

        if self.sim is None:
            raise ValueError("save(): only a simulated result (a distributed run's folder is written as it runs)")
        self.summary = write_run(self.sim, Path(out), arrays=arrays, extra_summary=extra_summary)
        self.path = Path(out)
        return self.summary

    def plot_errors(self, filter: int = 0, sat: int | None = None, *, sigma: float = 3.0, fig: Figure | None = None) -> Figure:
        """Filter ``filter``'s attitude (deg) and position (m) errors of satellite ``sat``
        (default: its own) per axis against ±``sigma``σ of its covariance and, when the run
        has one, ±``sigma``√ of the Cramér–Rao bound on that axis (dashed: the band no
        estimator fed the same measurements can shrink below)."""
        import matplotlib.pyplot as plt

        sat = filter if sat is None else sat
        df = self.errors
        d = df[(df["filter"] == filter) & (df["sat"] == sat)]
        if fig is None:
            fig = plt.figure(figsize=(10, 5.2), layout="constrained")
        axs = fig.subplots(2, 3, sharex=True)
        bound = getattr(self._data, "bound", None) if self._data is not None else None
        for row, (q, unit, scale) in enumerate((("att", "deg", np.degrees(1.0)), ("pos", "m", 1.0))):
            for col, x in enumerate(_AXES):
                ax = axs[row, col]
                err = d[f"{q}_err_{x}_{'rad' if q == 'att' else 'm'}"] * scale
                s = sigma * d[f"{q}_sigma_{x}_{'rad' if q == 'att' else 'm'}"] * scale
                ax.fill_between(d["t_s"], -s, s, color="tab:blue", alpha=0.15, lw=0, label=f"±{sigma:g}σ")
                ax.plot(d["t_s"], err, color="tab:red", lw=1.0, label="error")
                axes_var = None if bound is None else (bound.att_axes_rad2 if q == "att" else bound.pos_axes_m2)
                if axes_var is not None:
                    b = sigma * np.sqrt(axes_var[:, sat, col]) * scale
                    t = self.data.t_s
                    ax.plot(t, b, color="k", lw=0.8, ls="--", label=f"±{sigma:g}√bound")
                    ax.plot(t, -b, color="k", lw=0.8, ls="--")
                ax.set_title(f"{'attitude' if q == 'att' else 'position'} {x} [{unit}]", fontsize=9)
                if row == 1:
                    ax.set_xlabel("t [s]")
        axs[0, 0].legend(fontsize=8, loc="upper right")
        who = "its own satellite" if sat == filter else f"satellite {sat}"
        fig.suptitle(f"{self.scenario.name}: filter {filter} ({self.summary.get('estimator', 'full')}) estimating {who}", fontsize=10)
        return fig


# -- running --------------------------------------------------------------------------------------
def simulate(scenario: Scenario | str | Path | Mapping[str, Any] | None = None, *, seed: int | None = None,
             out: str | Path | None = None, arrays: bool = True, scene: bool | str | Path | None = None,
             progress: Progress | None = None, measurements: list | None = None, **overrides: Any) -> Result:
    """Run every satellite's filter in this process (``swarm sim``; seconds for small swarms).

    ``scenario``: anything :func:`load_scenario` takes; ``overrides``: dotted keys as
    keywords (``**{"estimator.kind": "ci"}``) or top-level fields (``duration_s=30``).
    ``out``: also write the run folder (summary.json, scenario.yaml, with ``arrays`` the npz
    files, and ``scene.mcap``, the 3-D scene for Foxglove, unless ``scene`` is False);
    ``scene``: a path writes the scene there. ``measurements`` (rendered scenarios, a list):
    receives every vision measurement. Same scenario and seed, same numbers as ``swarm sim``
    and ``swarm run``, bit for bit."""
    from swarm.record.scene_file import SCENE_FILE, SceneFile
    from swarm.simulation import simulate_scenario

    sc = _scenario(scenario, seed, overrides)
    scene_path: Path | None = None
    if isinstance(scene, (str, Path)):
        scene_path = Path(scene)
    elif out is not None and scene is not False:
        scene_path = Path(out) / SCENE_FILE
    elif scene is True:
        raise ValueError("simulate(scene=True) needs out= (or scene=<path>)")
    if scene_path is not None:
        with SceneFile(sc, scene_path) as hook:
            r = simulate_scenario(sc, progress=progress, measurements=measurements, on_step=hook)
    else:
        r = simulate_scenario(sc, progress=progress, measurements=measurements)
    res = Result(sc, r.summary(), "simulate", sim=r)
    if out is not None:
        res.save(out, arrays=arrays)
    return res


def run(scenario: Scenario | str | Path | Mapping[str, Any] | None = None, *, out: str | Path | None = None, seed: int | None = None,
        live: str | None = None, timeout: float | None = None, routers: int = 1, agents: Mapping[int, str] | None = None,
        progress: Progress | None = None, log: Callable[[str], None] | None = None,
        on_start: Callable[[Any], None] | None = None, cluster: Any = None, **overrides: Any) -> Result:
    """Run the swarm distributed (``swarm run``): a Zenoh router, the recorder, the world, the
    selector and one agent process per satellite on this machine, in lockstep; the result is
    read from the recording (``out/run.mcap``; ``out`` defaults to a new temporary folder).

    ``live``: ``"HOST:PORT"`` also serves the live 3-D view there (:mod:`swarm.live`).
    ``agents``: satellite → the command line of an agent of another language. SIGINT,
    SIGTERM and SIGHUP stop it cleanly (the result then covers the steps recorded and
    :attr:`Result.outcome` says why). ``on_start(swarm)``: called once every process is up.
    ``cluster``: ``"ray://HOST:PORT"`` runs it over a Ray cluster, ``"local-ray[:N]"`` over N
    Ray nodes started here for the run (:mod:`swarm.cluster`, docs/cluster.md)."""
    from swarm.outputs import write_json
    from swarm.supervise.launch import Interrupted, LocalSwarm
    from swarm.supervise.outcome import run_outcome

    sc = _scenario(scenario, seed, overrides)
    if agents:
        cmds = {**sc.emulator.agent_commands, **{int(k): str(v) for k, v in agents.items()}}
        sc = load_scenario(sc, overrides={"emulator.agent_commands": cmds})
    folder = Path(out) if out is not None else Path(tempfile.mkdtemp(prefix=f"swarm-run-{sc.name}-"))
    say = log or (lambda s: None)
    if cluster is not None:
        from swarm.cluster.swarm import RaySwarm

        if live is not None or routers != 1:
            raise ValueError("--cluster runs a router per node (no --routers) and has no live view yet (no --live)")
        if isinstance(cluster, str):
            swarm: LocalSwarm = RaySwarm(sc, folder, cluster, log=say)
        else:  # a swarm.cluster.local.LocalRayCluster the caller started and keeps
            swarm = RaySwarm(sc, folder, "local-ray", log=say, local_cluster=cluster)
    else:
        swarm = LocalSwarm(sc, folder, log=say, routers=routers, live=live)
    code: int | None = 1
    with swarm.handling_signals():
        try:
            swarm.start()
            if on_start is not None:
                on_start(swarm)
            code = swarm.run_to_end(progress=progress, timeout=timeout)
        except Interrupted:
            code = None
        finally:
            swarm.stop()
    outcome = run_outcome(sc, folder / "run.mcap", run=swarm.run, world_exit_code=code, interrupted=swarm.interrupted,
                          broken=swarm.broken, broken_code=swarm.broken_code, router_faults=swarm.router_faults, log=say,
                          router_gate=swarm.gate_counts())
    write_json(folder / "summary.json", outcome.summary)
    return Result(sc, outcome.summary, "run", folder, recording=folder / "run.mcap", outcome=outcome)


# -- studies --------------------------------------------------------------------------------------
class MonteCarlo:
    """Runs of one scenario over seeds S, S+1, ... (:func:`monte_carlo`)."""

    def __init__(self, doc: dict, path: Path):
        self.doc = doc  # mc.json
        self.path = path

    def __repr__(self) -> str:
        return f"MonteCarlo({self.doc.get('scenario')!r}: {self.doc.get('runs_ok')} of {self.doc.get('runs')} runs, {self.path})"

    @property
    def stats(self) -> pd.DataFrame:
        """Mean, std, min and max over the runs of every ``rms*``, ``nees``, ``gate`` and
        ``timing`` field of the summaries."""
        import pandas as pd

        return pd.DataFrame.from_dict(self.doc["stats"], orient="index")

    @property
    def per_run(self) -> pd.DataFrame:
        """One row per run that finished: its seed, time-RMS errors and mean NEES."""
        import pandas as pd

        rows = [{"seed": r["seed"], **_flat(r["rms"], "rms."), **_flat(r["rms_second_half"], "rms_second_half."),
                 "nees_mean": r["nees_mean"]} for r in self.doc["per_run"]]
        return pd.DataFrame(rows)

    @property
    def failed(self) -> list[dict]:
        return list(self.doc.get("failed") or [])

    def result(self, i: int) -> Result:
        """Run i's folder (written with ``arrays=True``)."""
        return Result.load(self.path / f"run_{i:04d}")


def _flat(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, Mapping):
            out |= _flat(v, f"{prefix}{k}.")
        else:
            out[f"{prefix}{k}"] = v
    return out


def _out(out: str | Path | None, what: str) -> Path:
    return Path(out) if out is not None else Path(tempfile.mkdtemp(prefix=f"swarm-{what}-"))


def monte_carlo(scenario: Scenario | str | Path | Mapping[str, Any] | None, runs: int, *, out: str | Path | None = None,
                seed: int | None = None, workers: int = 2, arrays: bool = False, cluster: str | None = None, resume: bool = False,
                progress: Progress | None = None, log: Callable[[str], None] | None = None, **overrides: Any) -> MonteCarlo:
    """``runs`` in-process runs with seeds S + i (S: ``seed``, default the scenario's), on
    ``workers`` local processes or the Dask scheduler at ``cluster`` (``swarm mc``). Writes
    ``out`` (default: a temporary folder): ``run_XXXX/``, ``results.jsonl``, ``mc.json``."""
    from swarm.studies.mc import run_mc

    sc = _scenario(scenario, None, overrides)
    folder = _out(out, "mc")
    doc = run_mc(sc, runs, folder, seed=seed, workers=workers, arrays=arrays, progress=progress, cluster=cluster, resume=resume,
                 log=log)
    return MonteCarlo(doc, folder)


class Comparison:
    """Paired runs of variants of one scenario over the same seeds (:func:`compare`)."""

    def __init__(self, doc: dict, path: Path, metrics: Sequence[str]):
        self.doc = doc
        self.path = path
        self.metrics = list(metrics)

    def __repr__(self) -> str:
        return f"Comparison({self.doc.get('scenario')!r}: {', '.join(self.variants)} over {len(self.doc.get('seeds', []))} seeds)"

    @property
    def variants(self) -> list[str]:
        return list(self.doc.get("variants") or self.doc.get("strategies") or [])

    @property
    def failed(self) -> list[dict]:
        """The runs that failed: variant (or strategy), seed and error."""
        return list(self.doc.get("failed") or [])

    @property
    def per_run(self) -> pd.DataFrame:
        """One row per (variant, seed) run; a RuntimeError when no seed has every variant."""
        import pandas as pd

        if not self.doc.get("seeds") and self.failed:
            f = self.failed[0]
            raise RuntimeError(f"every paired run failed ({len(self.failed)}); e.g. {f.get('variant', f.get('strategy'))} "
                               f"seed {f['seed']}: {f['error']}")
        rows = []
        for v, runs in (self.doc.get("per_run") or {}).items():
            for r in runs:
                rows.append({"variant": v, **{k: x for k, x in r.items() if not isinstance(x, (dict, list))}})
        return pd.DataFrame(rows)

    @property
    def summary(self) -> pd.DataFrame:
        """Mean and standard deviation of each metric per variant (rows: variants)."""
        df = self.per_run
        if df.empty:
            return df
        cols = [m for m in self.metrics if m in df.columns]
        g = df.groupby("variant", sort=False)[cols]
        out = g.mean().add_suffix(" mean").join(g.std(ddof=1).add_suffix(" std"))
        return out[[c for m in cols for c in (f"{m} mean", f"{m} std")]]


#: What :func:`compare` reports for variants (the summary's fields, flattened).
COMPARE_METRICS = ("rms.others.att_rad", "rms.others.pos_m", "rms_second_half.others.att_rad", "rms_second_half.others.pos_m",
                   "rms.self.att_rad", "rms.self.pos_m", "nees.mean", "relative.rms.pos_m", "traffic.bytes_per_sat_per_s_mean",
                   "cpu.filter_step_ms_median")


def variant_run(data: dict, overrides: dict, seed: int) -> dict:
    """One run of a comparison (a study task: plain values in and out): the scenario
    ``data`` with the variant's dotted ``overrides`` and ``seed``; its summary's metrics."""
    sc = load_scenario(data, seed=seed, overrides=overrides)
    from swarm.simulation import simulate_scenario

    flat = _flat(simulate_scenario(sc).summary())
    return {"seed": seed, **{m: flat.get(m) for m in COMPARE_METRICS}}


def compare(scenario: Scenario | str | Path | Mapping[str, Any] | None, *, strategies: Sequence[str] | None = None,
            estimators: Sequence[str] | None = None, variants: Mapping[str, Mapping[str, Any]] | None = None, runs: int = 5,
            seed: int | None = None, workers: int = 2, out: str | Path | None = None, cluster: str | None = None,
            resume: bool = False, progress: Progress | None = None, log: Callable[[str], None] | None = None,
            **overrides: Any) -> Comparison:
    """Paired in-process runs of variants of a scenario over the same seeds S … S+runs−1
    (the same truth and sensor noise in every variant: differences are the variant's).

    Give one of: ``strategies`` (selection strategies: ``swarm compare``, with its
    compare.json, compare.md and heat maps in ``out``), ``estimators`` (``estimator.kind``
    of each variant) or ``variants`` (name → dotted overrides, e.g. ``{"gate off":
    {"filter.gate.enabled": False}}``). Runs on ``workers`` local processes (1: this one) or
    the Dask scheduler at ``cluster``; ``out`` defaults to a temporary folder."""
    given = [x is not None for x in (strategies, estimators, variants)]
    if sum(given) != 1:  # (before any folder is made: a refused call leaves nothing behind)
        raise ValueError("compare(): give exactly one of strategies=, estimators=, variants=")
    sc = _scenario(scenario, None, overrides)
    folder = _out(out, "compare")
    if strategies is not None:
        from swarm.studies.compare import METRICS, run_compare

        doc = run_compare(sc, runs, folder, strategies=list(strategies), seed=seed, workers=workers, progress=progress,
                          cluster=cluster, resume=resume, log=log)
        return Comparison(doc, folder, [k for k, _ in METRICS] + ["nees_mean", "select_ms_median"])
    if estimators is not None:
        variants = {e: {"estimator.kind": e} for e in estimators}
    assert variants is not None
    return _compare_variants(sc, {str(k): dict(v) for k, v in variants.items()}, runs, folder, seed, workers, cluster, resume,
                             progress, log)


def _compare_variants(sc: Scenario, variants: dict[str, dict], runs: int, folder: Path, seed: int | None, workers: int,
                      cluster: str | None, resume: bool, progress: Progress | None, log) -> Comparison:
    from swarm.outputs import write_json
    from swarm.studies.executor import ResultStore, open_executor, run_study

    for ov in variants.values():  # a bad variant fails here, naming the field, before anything runs
        load_scenario(sc, overrides=ov)
    folder.mkdir(parents=True, exist_ok=True)
    base = sc.seed if seed is None else seed
    seeds = [base + i for i in range(runs)]
    data = sc.model_dump(mode="json")
    jobs = {f"{v}@{s}": (data, ov, s) for s in seeds for v, ov in variants.items()}
    store = ResultStore(folder / "results.jsonl", resume=resume)
    try:
        with open_executor(workers, cluster) as ex:
            st = run_study(ex, variant_run, jobs, store=store, progress=progress, log=log)
    finally:
        store.close()
    ok = [s for s in seeds if all(f"{v}@{s}" in st.results for v in variants)]
    doc = {
        "scenario": sc.name, "n_sats": sc.n_sats, "duration_s": sc.duration_s, "variants": list(variants),
        "overrides": variants, "seeds": ok, "seeds_dropped": [s for s in seeds if s not in ok],
        "failed": [{"variant": v, "seed": s, "error": st.errors[f"{v}@{s}"]} for s in seeds for v in variants if f"{v}@{s}" in st.errors],
        "backend": ex.description,
        "per_run": {v: [st.results[f"{v}@{s}"] for s in ok] for v in variants},
    }
    write_json(folder / "compare.json", doc)
    return Comparison(doc, folder, COMPARE_METRICS)
