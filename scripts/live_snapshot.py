#!/usr/bin/env python3
"""A picture of the live view without Foxglove: run a swarm with ``--live``, read its scene
over the Foxglove WebSocket protocol like any client (``swarm.live.client``: every channel,
decoded with its advertised schema) and draw what a client received with matplotlib — the 3D
panel's channels at one step (an overview of the formation and a close-up of one satellite),
the Plot panels' ``/errors/<i>`` series and the Log panel's ``/foxglove/faults``. It is the
README's docs/live-view.png; it is not a Foxglove screenshot (Foxglove's app is a web app
served from foxglove.dev, not installable from PyPI, crates.io or Debian, so it cannot be
run on a machine without the internet).

    python scripts/live_snapshot.py [--scenario scenarios/demo-faults.yaml] [--step 28] [--out docs/live-view.png]
"""

from __future__ import annotations  # noqa: I001  (swarm before numpy: it chooses the numeric kernels first)

import argparse
import pickle
import threading
from collections import defaultdict
from pathlib import Path

import swarm  # first: the numeric settings before numpy

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "runs" / "live-snapshot"
BG, FG = "#10141c", "#d8dee9"
PALETTE = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"]


def collect_live(scenario: Path, step_hint: int, sets: dict) -> tuple[list, swarm.Result]:
    from swarm.live.client import collect

    got: list = []
    threads = []

    def start(sw) -> None:
        import json

        url = json.loads((sw.out / "live.json").read_text())["url"]
        th = threading.Thread(target=lambda: got.extend(collect(url, until=lambda ms: False, timeout_s=3600, ok_if_closed=True)),
                              daemon=True)
        th.start()
        threads.append(th)

    res = swarm.run(scenario, live="127.0.0.1:0", on_start=start, out=RUN, **sets)
    for th in threads:
        th.join(60)
    with open(RUN / "received.pkl", "wb") as f:  # what the client got, raw (--reuse draws it again)
        pickle.dump([(m.topic, m.schema_name, m.log_ns, m.data) for m in got], f)
    return got, res


def reuse() -> tuple[list, swarm.Result]:
    """The messages of the last run again, decoded with the recording's schemas."""
    from swarm.live.client import Received, message_class
    from swarm.record.mcaplog import iter_records

    schemas = {}
    for schema, ch, _m in iter_records(RUN / "run.mcap"):
        if ch.topic.startswith("/") and ch.topic not in schemas:
            schemas[ch.topic] = message_class(schema.name, schema.data)
    with open(RUN / "received.pkl", "rb") as f:
        raw = pickle.load(f)
    return [Received(t, s, ns, d, schemas[t].FromString(d)) for t, s, ns, d in raw], swarm.Result.load(RUN)


def _rgba(c) -> tuple:
    return (c.r, c.g, c.b, max(c.a, 0.15))


def _xyz(p) -> np.ndarray:
    return np.array([p.x, p.y, p.z])


def _quat(q) -> Rotation:
    return Rotation.from_quat([q.x, q.y, q.z, q.w])


_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
_EDGES = [(i, j) for i in range(8) for j in range(i + 1, 8) if np.abs(_CORNERS[i] - _CORNERS[j]).sum() == 2]


def _cube(ax, center, rot: Rotation, size, color, alpha=0.9, lw=0.8):
    c = rot.apply(_CORNERS * (0.5 * np.asarray(size))) + center
    for i, j in _EDGES:
        ax.plot(*zip(c[i], c[j]), color=color, alpha=alpha, lw=lw)


def _ellipsoid(ax, center, rot: Rotation, diameters, color):
    u, v = np.mgrid[0:2 * np.pi:18j, 0:np.pi:10j]
    pts = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)], -1) * (0.5 * np.asarray(diameters))
    w = rot.apply(pts.reshape(-1, 3)).reshape(pts.shape) + center
    ax.plot_wireframe(w[..., 0], w[..., 1], w[..., 2], color=color, lw=0.4, alpha=0.7)


def latest_before(msgs: list, topic: str, t_ns: int):
    best = None
    for m in msgs:
        if m.topic == topic and m.log_ns <= t_ns and (best is None or m.log_ns >= best.log_ns):
            best = m
    return best


def draw(msgs: list, res: swarm.Result, step: int, out: Path, focus: int = 1) -> None:
    n = res.scenario.n_sats
    truths = [m for m in msgs if m.topic == "/foxglove/truth"]
    ks = {int({kv.key: kv.value for kv in m.msg.entities[0].metadata}["k"]): m for m in truths}
    k = min(ks, key=lambda x: abs(x - step))
    t_ns = ks[k].log_ns
    tf = latest_before(msgs, "/foxglove/tf", t_ns + 1)
    frames = {t.child_frame_id: (_xyz(t.translation), _quat(t.rotation)) for t in tf.msg.transforms}
    fig = plt.figure(figsize=(15, 9.2), facecolor=BG)
    gs = fig.add_gridspec(3, 3, height_ratios=[1, 1, 0.82], width_ratios=[1.15, 1.15, 1.0], hspace=0.32, wspace=0.12)
    over = fig.add_subplot(gs[0:2, 0:2], projection="3d")
    close = fig.add_subplot(gs[0, 2], projection="3d")
    zoom = fig.add_subplot(gs[1, 2], projection="3d")
    from matplotlib.ticker import MaxNLocator

    for ax in (over, close, zoom):
        if ax is not over:
            for a in (ax.xaxis, ax.yaxis, ax.zaxis):
                a.set_major_locator(MaxNLocator(3))
        ax.set_facecolor(BG)
        ax.xaxis.set_pane_color((0.1, 0.12, 0.16, 1))
        ax.yaxis.set_pane_color((0.1, 0.12, 0.16, 1))
        ax.zaxis.set_pane_color((0.1, 0.12, 0.16, 1))
        ax.tick_params(colors=FG, labelsize=7)
        for a in (ax.xaxis, ax.yaxis, ax.zaxis):
            a.label.set_color(FG)
        ax.set_xlabel("x radial [m]", fontsize=8)
        ax.set_ylabel("y along-track [m]", fontsize=8)
        ax.set_zlabel("z normal [m]", fontsize=8)
    # The truth: labelled bodies (the overview draws them 6× larger to be seen at all).
    for e in ks[k].msg.entities:
        c = e.cubes[0]
        for ax, scale in ((over, 6.0), (close, 1.0)):
            _cube(ax, _xyz(c.pose.position), _quat(c.pose.orientation), np.array([c.size.x, c.size.y, c.size.z]) * scale, _rgba(c.color))
        p = _xyz(c.pose.position)
        over.text(p[0], p[1], p[2] + 1.5, e.texts[0].text, color=FG, fontsize=9)
    # Measurement lines and links of that step.
    for topic, lw in (("/foxglove/measurements", 1.0), ("/foxglove/links", 2.2)):
        seen = {}
        for m in msgs:
            if m.topic == topic and m.log_ns <= t_ns + 2e9 and m.log_ns >= t_ns - 1:
                for e in m.msg.entities:
                    seen.setdefault(e.id, e)
        for e in seen.values():
            for line in e.lines:
                pts = np.array([_xyz(p) for p in line.points]).reshape(-1, 2, 3)
                for a, b in pts:
                    over.plot(*zip(a, b), color=_rgba(line.color), lw=lw, alpha=0.55)
    # Camera frusta (in each body frame; red: a camera a fault turned off).
    cams = latest_before(msgs, "/foxglove/cameras", t_ns + 1)
    off_cams = []
    for e in cams.msg.entities:
        if e.frame_id not in frames:
            continue
        r, rot = frames[e.frame_id]
        off_cams += [f"{e.frame_id} {kv.key}" for kv in e.metadata if kv.value == "off"]
        for line in e.lines:
            pts = rot.apply(np.array([_xyz(p) for p in line.points])) + r
            for ax, grow in ((over, 4.0), (close, 1.0)):
                if ax is over and e.frame_id != f"sat{focus}" and line.color.r < 0.9:
                    continue  # the overview: only the focus satellite's frusta and the cameras that are off
                q = (pts - r) * grow + r
                for a, b in q.reshape(-1, 2, 3):
                    ax.plot(*zip(a, b), color=_rgba(line.color), lw=0.7)
    # Each filter's estimate of the focus satellite (its centre) and its 3σ position ellipsoid,
    # around the true centre. A filter whose agent is dead shows its last estimate (stale).
    rf, _ = frames[f"sat{focus}"]
    zoom.scatter(*rf, color="white", s=30, marker="+", label="truth")
    reach = 0.02
    for i in range(n):
        est = latest_before(msgs, f"/foxglove/est/{i}", t_ns + 3e9)
        if est is None:
            continue
        for e in est.msg.entities:
            if e.id != f"est{i}-sat{focus}":
                continue
            s = e.spheres[0]
            c = _xyz(s.pose.position)
            shown_k = max((kk for kk, m in ks.items() if m.log_ns <= est.log_ns), default=k)
            stale = shown_k < k - 2
            zoom.scatter(*c, color=PALETTE[i], s=14, label=f"filter {i}" + (" (stale: agent dead)" if stale else ""))
            _ellipsoid(zoom, c, _quat(s.pose.orientation), [s.size.x, s.size.y, s.size.z], PALETTE[i])
            reach = max(reach, float(np.abs(c - rf).max() + 0.5 * max(s.size.x, s.size.y, s.size.z)))
    zoom.set(xlim=(rf[0] - reach, rf[0] + reach), ylim=(rf[1] - reach, rf[1] + reach), zlim=(rf[2] - reach, rf[2] + reach))
    zoom.set_title(f"/foxglove/est/<i>: each filter's estimate of sat {focus} and its 3σ ellipsoid", color=FG, fontsize=9)
    zoom.legend(fontsize=7, facecolor=BG, labelcolor=FG, edgecolor="#3a4a60", loc="upper left")
    span = 1.8
    close.set(xlim=(rf[0] - span, rf[0] + span), ylim=(rf[1] - span, rf[1] + span), zlim=(rf[2] - span, rf[2] + span))
    close.set_title(f"/foxglove/cameras: sat {focus}'s six face cameras (frame sat{focus})", color=FG, fontsize=9)
    over.set_title(f"/foxglove/truth, tf, measurements, links, cameras at step {k} (t = {k * res.scenario.dt_s:g} s)"
                   + ("; off: " + ", ".join(off_cams) if off_cams else ""), color=FG, fontsize=10)
    over.text2D(0.0, 0.0, "bodies drawn 6× and sat 1's frusta 4× their size to be seen at this scale", transform=over.transAxes,
                color="#8a94a6", fontsize=8)
    over.view_init(elev=28, azim=-58)
    close.view_init(elev=22, azim=-40)
    zoom.view_init(elev=22, azim=-40)
    # Plot panels from /errors/<i> (every message the client received), and the faults log.
    series: dict[int, list] = defaultdict(list)
    for m in msgs:
        if m.topic.startswith("/errors/"):
            e = m.msg
            series[e.own].append((e.t_s, e.own_pos_err_m, e.own_pos_3sigma_m, e.nees_mean))
    axp, axn, axl = (fig.add_subplot(gs[2, j]) for j in range(3))
    for i, rows in sorted(series.items()):
        a = np.array(sorted(rows))
        gaps = np.nonzero(np.diff(a[:, 0]) > 4 * res.scenario.dt_s)[0]  # a dead agent's silence: a gap, not a line
        a = np.insert(a, gaps + 1, np.nan, axis=0)
        axp.plot(a[:, 0], a[:, 1] * 100, color=PALETTE[i], lw=1, label=f"sat {i}")
        axp.plot(a[:, 0], a[:, 2] * 100, color=PALETTE[i], lw=0.8, ls=":", alpha=0.8)
        axn.plot(a[:, 0], a[:, 3], color=PALETTE[i], lw=1, label=f"filter {i}")
    axn.axhline(6, color=FG, lw=0.6, ls="--")
    axp.set_title("/errors/<i>.own_pos_err_m (dotted: own_pos_3sigma_m) [cm]", color=FG, fontsize=9)
    axn.set_title("/errors/<i>.nees_mean (6: consistent)", color=FG, fontsize=9)
    for ax in (axp, axn, axl):
        ax.set_facecolor(BG)
        ax.tick_params(colors=FG, labelsize=7)
        for sp in ax.spines.values():
            sp.set_color("#3a4a60")
    for ax in (axp, axn):
        ax.axvline(k * res.scenario.dt_s, color="#ffffff", lw=0.6, alpha=0.5)
        ax.set_xlabel("t [s]", color=FG, fontsize=8)
        ax.legend(fontsize=7, ncols=2, facecolor=BG, labelcolor=FG, edgecolor="#3a4a60")
    axl.set_title("/foxglove/faults (foxglove.Log)", color=FG, fontsize=9)
    axl.set_xticks([])
    axl.set_yticks([])
    logs = sorted((m for m in msgs if m.topic == "/foxglove/faults"), key=lambda m: m.log_ns)
    lvl = {2: ("INFO", "#88c0d0"), 3: ("WARN", "#ebcb8b"), 4: ("ERROR", "#bf616a")}
    for j, m in enumerate(logs[-9:]):
        name, col = lvl.get(m.msg.level, ("?", FG))
        text = f"{name:5s} {m.msg.name}: {m.msg.message}".replace(" (scheduled)", "")
        axl.text(0.01, 0.93 - j * 0.105, text[:74] + ("…" if len(text) > 74 else ""), color=col, fontsize=6.8, family="monospace",
                 transform=axl.transAxes, va="top")
    fig.suptitle("The live view's scene as a client receives it from `swarm run --live` (Foxglove WebSocket protocol, decoded with the "
                 "advertised schemas)\ndrawn with matplotlib, panel by panel as docs/foxglove-layout.json arranges them — not a "
                 "screenshot of Foxglove", color=FG, fontsize=10.5)
    fig.savefig(out, dpi=100, facecolor=BG)
    print(f"wrote {out} (step {k}; {len(msgs)} messages received)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenario", default=str(ROOT / "scenarios" / "demo-faults.yaml"))
    p.add_argument("--step", type=int, default=28)
    p.add_argument("--focus", type=int, default=1, help="the satellite of the close-up")
    p.add_argument("--out", default=str(ROOT / "docs" / "live-view.png"))
    p.add_argument("--max-rtf", type=float, default=5.0, help="lockstep no faster than this (the view then draws every step)")
    p.add_argument("--reuse", action="store_true", help="draw the messages of the last run again (runs/live-snapshot)")
    a = p.parse_args()
    # Lockstep (the numbers of `swarm sim`), held to 5× real time so that the view draws every step.
    sets = {"emulator.lockstep_max_realtime_factor": a.max_rtf}
    msgs, res = reuse() if a.reuse else collect_live(Path(a.scenario), a.step, sets)
    draw(msgs, res, a.step, Path(a.out), a.focus)


if __name__ == "__main__":
    main()
