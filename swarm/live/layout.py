"""The Foxglove layout that opens the swarm's scene: live (``swarm run --live``), recorded
(``run.mcap``) and simulated (``scene.mcap``), all on the channels of
:mod:`swarm.record.scene`.

The layout is Foxglove's layout file (``configById`` / ``layout``: what *Layouts → Import from
file* reads): a 3D panel in the Hill frame (``hcw``) with the true bodies, every filter's
estimates and 3σ ellipsoids, the measurement lines, the links and the camera frusta; Plot
panels of every filter's own and others' position errors, its own error against 3σ and its
mean NEES (``/errors/<i>``); a Log panel of the faults (``/foxglove/faults``).
``docs/foxglove-layout.json`` is :func:`layout` of 10 satellites (a smaller swarm leaves some
series empty); ``swarm live layout --sats N`` writes one for N.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from swarm.record.scene import LINK_STATES

__all__ = ["layout", "write_layout", "layout_topics", "SHIPPED_SATS"]

#: The swarm size of the shipped ``docs/foxglove-layout.json``.
SHIPPED_SATS = 10

_COLORS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"]


def _series(path: str, label: str, color: str | None = None) -> dict[str, Any]:
    s: dict[str, Any] = {"value": path, "enabled": True, "timestampMethod": "receiveTime", "label": label}
    if color:
        s["color"] = color
    return s


def _plot(title: str, paths: list[dict], y_min: float | None = None) -> dict[str, Any]:
    cfg: dict[str, Any] = {
        "foxglovePanelTitle": title,
        "paths": paths,
        "showXAxisLabels": True,
        "showYAxisLabels": True,
        "showLegend": True,
        "legendDisplay": "floating",
        "showPlotValuesInLegend": False,
        "isSynced": True,
        "xAxisVal": "timestamp",
        "sidebarDimension": 240,
    }
    if y_min is not None:
        cfg["minYValue"] = y_min
    return cfg


def layout(n_sats: int = SHIPPED_SATS) -> dict[str, Any]:
    """The layout (a JSON-able dict) for a swarm of ``n_sats`` satellites."""
    col = lambda i: _COLORS[i % len(_COLORS)]  # noqa: E731
    scene_topics = ["/foxglove/tf", "/foxglove/truth", "/foxglove/measurements", "/foxglove/links", "/foxglove/cameras",
                    *(f"/foxglove/est/{i}" for i in range(n_sats))]
    three_d = {
        "foxglovePanelTitle": "swarm (Hill frame: x radial, y along-track, z orbit normal)",
        "cameraState": {"distance": 60.0, "perspective": True, "phi": 55.0, "thetaOffset": 35.0, "target": [0, 0, 0],
                        "targetOffset": [0, 0, 0], "targetOrientation": [0, 0, 0, 1], "fovy": 45.0, "near": 0.01, "far": 5000.0},
        "followMode": "follow-none",
        "followTf": "hcw",
        "scene": {"enableStats": False, "backgroundColor": "#10141c", "transforms": {"showLabel": False, "axisScale": 0.6}},
        "transforms": {},
        "topics": {t: {"visible": True} for t in scene_topics},
        "layers": {"grid": {"visible": True, "frameLocked": True, "label": "Grid (5 m)", "instanceId": "grid", "layerId": "foxglove.Grid",
                            "frameId": "hcw", "size": 60, "divisions": 12, "lineWidth": 1, "color": "#3a4a6088",
                            "position": [0, 0, 0], "rotation": [0, 0, 0], "order": 1}},
        "publish": {"type": "point", "poseTopic": "/move_base_simple/goal", "pointTopic": "/clicked_point",
                    "poseEstimateTopic": "/initialpose", "poseEstimateXDeviation": 0.5, "poseEstimateYDeviation": 0.5,
                    "poseEstimateThetaDeviation": 0.26179939},
        "imageMode": {},
    }
    configs: dict[str, Any] = {
        "3D!swarm": three_d,
        "Plot!own": _plot("own position error [m] and its 3σ (dotted: 3σ)", [
            p for i in range(n_sats) for p in (_series(f"/errors/{i}.own_pos_err_m", f"sat {i}", col(i)),
                                                _series(f"/errors/{i}.own_pos_3sigma_m", f"sat {i} 3σ", col(i) + "66"))], 0.0),
        "Plot!others": _plot("others' position error, RMS over the satellites each filter tracks [m]", [
            _series(f"/errors/{i}.others_pos_err_rms_m", f"filter {i}", col(i)) for i in range(n_sats)], 0.0),
        "Plot!nees": _plot("NEES, mean over the satellites each filter tracks (6: consistent)", [
            _series(f"/errors/{i}.nees_mean", f"filter {i}", col(i)) for i in range(n_sats)], 0.0),
        "RosOut!faults": {"foxglovePanelTitle": "faults", "searchTerms": [], "minLogLevel": 1, "topicToRender": "/foxglove/faults"},
        "RawMessages!links": {"foxglovePanelTitle": "links this step: " + ", ".join(f"{n}" for n, _ in LINK_STATES),
                              "topicPath": "/foxglove/links.entities[0].metadata", "diffEnabled": False, "diffMethod": "custom",
                              "diffTopicPath": "", "showFullMessageForDiff": False, "expansion": "all"},
    }
    tree = {
        "direction": "row",
        "first": "3D!swarm",
        "second": {
            "direction": "column",
            "first": {"direction": "column", "first": "Plot!own", "second": "Plot!others", "splitPercentage": 50},
            "second": {"direction": "column", "first": "Plot!nees",
                       "second": {"direction": "row", "first": "RosOut!faults", "second": "RawMessages!links", "splitPercentage": 55},
                       "splitPercentage": 50},
            "splitPercentage": 55,
        },
        "splitPercentage": 58,
    }
    return {"configById": configs, "globalVariables": {}, "userNodes": {}, "linkedGlobalVariables": [],
            "playbackConfig": {"speed": 1.0}, "layout": tree}


def layout_topics(doc: dict[str, Any]) -> set[str]:
    """Every topic a layout reads (3D topics, the plots' and raw panels' message paths, logs)."""
    out: set[str] = set()
    for cfg in doc["configById"].values():
        out |= set((cfg.get("topics") or {}).keys())
        for p in cfg.get("paths") or []:
            out.add(p["value"].split(".", 1)[0])
        for key in ("topicToRender", "topicPath"):
            if cfg.get(key):
                out.add(cfg[key].split(".", 1)[0])
    return out


def write_layout(path: str | Path, n_sats: int = SHIPPED_SATS) -> Path:
    path = Path(path)
    path.write_text(json.dumps(layout(n_sats), indent=2, ensure_ascii=False) + "\n")
    return path
