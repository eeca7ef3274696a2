"""Rendered cameras in the distributed emulator: the world renders, the images travel on a
real loopback Zenoh bus, each agent measures its own. Same numbers as in-process."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from swarm_harness import run_swarm

from swarm.record.mcaplog import iter_messages
from swarm.simulation import measurement_model
from swarmcore.sim import simulate
from swarmrt.scenario_files import load_scenario

ROOT = Path(__file__).resolve().parents[1]

pytestmark = [pytest.mark.integration, pytest.mark.render, pytest.mark.slow]

SMALL_MONO = [
    "n_sats=3", "duration_s=4", "vision.mono_camera.width_px=800", "vision.mono_camera.height_px=800",
    "vision.mono_camera.focal_px=350", "vision.covariance.source=fixed", "initial.position_max_m=3.0",
    "initial.min_separation_m=2.0", "emulator.step_timeout_s=60",
]
SMALL_STEREO = ["n_sats=3", "duration_s=2", "vision.covariance.source=fixed", "emulator.step_timeout_s=60"]


def _same_as_in_process(sc, rec, summary):
    res = simulate(sc, measurement_model(sc))
    ref = res.summary()
    for key in ("rms", "rms_second_half", "per_pair", "nees", "gate", "nis"):
        assert summary[key] == ref[key], key
    np.testing.assert_array_equal(rec.est.r_H_m, res.est.r_H_m)
    np.testing.assert_array_equal(rec.est.q_BI, res.est.q_BI)
    return ref


def test_mono_images_on_the_bus_give_the_in_process_numbers(tmp_path):
    sc = load_scenario(ROOT / "scenarios" / "mono-5sat.yaml", [*SMALL_MONO, "emulator.record_images=true"])
    rec, summary, codes, _ = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0 and rec.alive.all()
    ref = _same_as_in_process(sc, rec, summary)
    # The filters did take image measurements (not an empty run that trivially agrees).
    assert ref["gate"]["accepted"] >= 0.9 * 6 * sc.steps * sc.n_sats
    # The recording keeps each Images message's metadata and, as asked, the pixels.
    topics = {}
    for topic, _schema, data, _log, _pub in iter_messages(tmp_path / "run" / "run.mcap"):
        topics.setdefault(topic.split("/sat/")[-1] if "/sat/" in topic else topic, []).append(data)
    assert len(topics["0/img"]) == sc.steps
    from swarmrt.bus.messages import Images

    rec_img = [Images.FromString(d) for d in topics["0/img"]]  # the camera models, the pixels left out
    assert any(m.views for m in rec_img)
    assert all(len(v.images_mono8) == 0 and v.width_px == 800 for m in rec_img for v in m.views)
    raw = [t for t in topics if t.startswith("/sat0/cam")]
    assert raw, "no foxglove.RawImage channel for satellite 0"
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    img = RawImage()
    img.ParseFromString(topics[raw[0]][0])
    assert (img.width, img.height, img.encoding, img.step) == (800, 800, "mono8", 800)
    assert len(img.data) == 800 * 800 and max(img.data) > 0  # something in view, not a blank frame


def test_stereo_images_on_the_bus_give_the_in_process_numbers(tmp_path):
    sc = load_scenario(ROOT / "scenarios" / "stereo-4sat.yaml", SMALL_STEREO)
    rec, summary, codes, _ = run_swarm(sc, tmp_path / "run")
    assert codes["world"] == 0 and rec.alive.all()
    ref = _same_as_in_process(sc, rec, summary)
    assert ref["gate"]["accepted"] >= 0.7 * 6 * sc.steps * sc.n_sats
