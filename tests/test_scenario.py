"""Scenario files: defaults, overrides and errors that name the field."""

import textwrap

import numpy as np
import pytest

from swarmcore import graphs
from swarmcore.scenario import Scenario
from swarmrt.scenario_files import ScenarioError, load_scenario, parse_overrides


def test_defaults_follow_table_4_1():
    sc = Scenario()
    assert sc.orbit.mean_motion_rad_s == 1.08e-3
    assert sc.sensors.gyro.arw_rad_sqrt_s == 3.16e-7 and sc.sensors.gyro.rrw_rad_s15 == 3.16e-10
    assert sc.sensors.star_tracker.sigma_rad == 2.9e-5 and sc.sensors.gps.sigma_m == 0.01
    assert sc.sensors.relative.sigma_att_rad == 0.03 and sc.sensors.relative.sigma_pos_m == 0.01
    assert sc.disturbances.torque_sigma_Nm_sqrt_s == 5e-6 and sc.disturbances.accel_sigma_m_s15 == 1e-8
    assert sc.initial.position_max_m == 10 and sc.initial.velocity_max_m_s == 0.005
    assert sc.initial.rate_max_rad_s == 0.006 and sc.dt_s == 1.0


def test_dissertation_inertia_refused_unless_allowed():
    with pytest.raises(ValueError, match="triangle inequality"):
        Scenario(spacecraft={"inertia_kg_m2": [1.67, 8.33, 3.67]})
    sc = Scenario(spacecraft={"inertia_kg_m2": [1.67, 8.33, 3.67], "allow_nonphysical_inertia": True})
    np.testing.assert_allclose(np.diag(sc.spacecraft.J()), [1.67, 8.33, 3.67])


def test_bad_file_value_names_the_field(tmp_path):
    f = tmp_path / "bad.yaml"
    f.write_text("n_sats: 4\nsensors:\n  gps:\n    sigma_m: -1\n")
    with pytest.raises(ScenarioError) as exc:
        load_scenario(f)
    msg = str(exc.value)
    assert "sensors.gps.sigma_m" in msg and str(f) in msg and "-1" in msg


def test_unknown_field_is_named(tmp_path):
    f = tmp_path / "typo.yaml"
    f.write_text("n_sats: 4\nfilter:\n  gaet: {enabled: false}\n")
    with pytest.raises(ScenarioError, match=r"filter\.gaet: unknown field"):
        load_scenario(f)


def test_yaml_syntax_error_names_the_file(tmp_path):
    f = tmp_path / "broken.yaml"
    f.write_text("n_sats: [4\n")
    with pytest.raises(ScenarioError, match="not valid YAML") as exc:
        load_scenario(f)
    assert str(f) in str(exc.value) and "line 1" in str(exc.value)


def test_set_overrides_any_field(tmp_path):
    f = tmp_path / "s.yaml"
    f.write_text(textwrap.dedent("""
        n_sats: 4
        graph: {kind: complete}
    """))
    sc = load_scenario(f, ["graph.kind=chain", "filter.gate.enabled=false", "sensors.relative.sigma_pos_camera_m=[0.1, 0.1, 0.05]"], seed=9)
    assert sc.graph.kind == "chain" and sc.filter.gate.enabled is False and sc.seed == 9
    assert sc.sensors.relative.sigma_pos_camera_m == [0.1, 0.1, 0.05]
    with pytest.raises(ScenarioError, match=r"graph\.kind"):
        load_scenario(f, ["graph.kind=ring"])
    with pytest.raises(ScenarioError, match=r"dotted\.key=value"):
        parse_overrides(["n_sats"])


def test_graph_matrix_validated_and_used():
    with pytest.raises(ValueError, match=r"graph.matrix: must be 3×3"):
        Scenario(n_sats=3, graph={"kind": "matrix", "matrix": [[1, 1], [1, 1]]})
    M = [[1, 1, 0], [0, 0, 1], [1, 0, 1]]
    sc = Scenario(n_sats=3, graph={"kind": "matrix", "matrix": M})
    G = graphs.incidence(3, "matrix", matrix=sc.graph.matrix)
    i, j = graphs.edges(G)
    assert list(zip(i.tolist(), j.tolist(), strict=True)) == [(0, 1), (1, 2), (2, 0)]
    assert G.diagonal().tolist() == [True, False, True]


@pytest.mark.parametrize(
    "kind,expected",
    [
        ("complete", 12),
        ("star", 3),
        ("chain", 3),
        ("duplex_chain", 6),
    ],
)
def test_topologies(kind, expected):
    G = graphs.incidence(4, kind)
    assert G[~np.eye(4, dtype=bool)].sum() == expected
    if kind == "star":
        assert G[:, 0].sum() == 4 and G[1:, 1:][~np.eye(3, dtype=bool)].sum() == 0


def test_every_shipped_scenario_loads():
    from pathlib import Path

    files = sorted(Path(__file__).resolve().parents[1].joinpath("scenarios").glob("*.yaml"))
    assert files
    for f in files:
        load_scenario(f)


def test_a_stall_fault_needs_its_length_and_only_timed_faults_take_one():
    from swarmcore.scenario import FaultSpec

    ok = FaultSpec(at_step=3, action="stall-world", down_s=12.0)
    assert ok.target is None and ok.down_s == 12.0
    assert FaultSpec(at_step=3, action="stall-router", target=1, down_s=2.0).target == 1
    with pytest.raises(ValueError, match="stall-agent needs down_s > 0"):
        FaultSpec(at_step=3, action="stall-agent", target=1)
    with pytest.raises(ValueError, match="stall-agent needs a target"):
        FaultSpec(at_step=3, action="stall-agent", down_s=2.0)
    with pytest.raises(ValueError, match="down_s is for actions restart-router, stall-agent"):
        FaultSpec(at_step=3, action="kill-agent", target=1, down_s=2.0)


def test_a_link_fault_names_what_it_does_and_needs_the_link_model():
    from swarmcore.scenario import FaultSpec, Scenario

    assert FaultSpec(at_step=2, action="link", target=1, peer=2, delay_s=1.5).delay_s == 1.5
    assert FaultSpec(at_step=2, action="link", target=1, state="off").peer is None
    with pytest.raises(ValueError, match="link needs state"):
        FaultSpec(at_step=2, action="link", target=1)
    with pytest.raises(ValueError, match="no link to itself"):
        FaultSpec(at_step=2, action="link", target=1, peer=1, state="off")
    with pytest.raises(ValueError, match="state on gives the link back"):
        FaultSpec(at_step=2, action="link", target=1, state="on", rate=0.3)
    with pytest.raises(ValueError, match="peer is for actions link and partition-nodes"):
        FaultSpec(at_step=2, action="kill-agent", target=1, peer=2)
    with pytest.raises(ValueError, match="delay_s is for action link"):
        FaultSpec(at_step=2, action="kill-agent", target=1, delay_s=2.0)
    with pytest.raises(ValueError, match="rate is for actions drop and link"):
        FaultSpec(at_step=2, action="kill-agent", target=1, rate=0.5)
    fault = {"at_step": 2, "action": "link", "target": 1, "state": "off"}
    with pytest.raises(ValueError, match=r"faults.0.action: link acts on the radio's link model.*links.enabled: false"):
        Scenario(n_sats=3, faults=[fault])
    with pytest.raises(ValueError, match=r"faults.0.peer: 5 is not a satellite id"):
        Scenario(n_sats=3, links={"enabled": True}, faults=[{**fault, "peer": 5}])
    assert Scenario(n_sats=3, links={"enabled": True}, faults=[fault]).faults[0].action == "link"


def test_cluster_faults_and_placement_name_what_they_need():
    from swarmcore.scenario import FaultSpec, Scenario

    assert FaultSpec(at_step=3, action="kill-node", target=2).target == 2
    with pytest.raises(ValueError, match="kill-node needs a target node"):
        FaultSpec(at_step=3, action="kill-node")
    ok = FaultSpec(at_step=3, action="partition-nodes", target=1, peer=2, down_s=10.0)
    assert (ok.target, ok.peer, ok.down_s) == (1, 2, 10.0)
    for bad in ({"peer": 1}, {"peer": 2, "down_s": None}, {}):
        with pytest.raises(ValueError, match="partition-nodes needs target and peer"):
            FaultSpec(at_step=3, action="partition-nodes", target=1, **{"down_s": 10.0, **bad})
    # A node index is not a satellite id: checked against the cluster when it runs.
    assert Scenario(n_sats=3, faults=[{"at_step": 1, "action": "kill-node", "target": 7}]).faults[0].target == 7
    sc = Scenario(n_sats=3, emulator={"placement": {"agents": [0, 1, 1], "recorder": 1}})
    assert sc.emulator.placement.agents == [0, 1, 1] and sc.emulator.placement.world == 0
    with pytest.raises(ValueError, match="2 node indices for 3 satellites"):
        Scenario(n_sats=3, emulator={"placement": {"agents": [0, 1]}})
