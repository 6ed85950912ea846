"""algorithm.graph at load: bad settings and disconnected graphs named at their YAML path; a
ring with a vehicle that goes silent refused for flight, at its event."""

import pytest
import yaml

from mission_runner.checks import flight_problems, parse_scenario
from mission_runner.errors import ConfigError
from tests.test_config import CONFIGS, base, problems_of


def with_graph(graph, vehicles=None):
    data = base()
    data["algorithm"]["graph"] = graph
    if vehicles is not None:
        data["vehicles"] = vehicles
    return data


@pytest.mark.parametrize(
    ("graph", "where", "rule"),
    [
        ({"kind": "edges", "edges": [[0, 1], [1, 1]]}, "algorithm.graph.edges[1]", "self loop"),
        (
            {"kind": "edges", "edges": [[0, 1], [1, 2], [2, 4]]},
            "algorithm.graph.edges[2]",
            "vehicle index 4 is not in 0..3",
        ),
        (
            {"kind": "edges", "edges": [[0, 1], [1, 2], [2, 3], [1, 0]]},
            "algorithm.graph.edges[3]",
            "[1, 0] repeats edges[0]",
        ),
        (
            {"kind": "edges", "edges": [[0, 1], [2, 3]]},
            "algorithm.graph",
            "vehicles {0,1} and {2,3} are not connected",
        ),
        ({"kind": "k_nearest"}, "algorithm.graph.k", "give k for kind k_nearest"),
        ({"kind": "ring", "k": 2}, "algorithm.graph.k", "give k for kind k_nearest"),
        ({"kind": "edges"}, "algorithm.graph.edges", "give edges for kind edges"),
        ({"kind": "k_nearest", "k": 0}, "algorithm.graph.k", "greater than or equal to 1"),
        ({"kind": "star"}, "algorithm.graph.kind", "'complete', 'ring', 'k_nearest' or 'edges'"),
    ],
)
def test_bad_graph_is_reported_at_its_yaml_path(graph, where, rule):
    problems = problems_of(with_graph(graph))
    assert any(location == where and rule in message for location, message in problems), problems


def test_k_nearest_that_leaves_two_clusters_apart_is_refused():
    far = [
        {"id": i + 1, "initial_position_m": [north, 0.0], "initial_phase_rad": 0.5 * i}
        for i, north in enumerate([0.0, 1.0, 50.0, 51.0])
    ]
    far[0]["senses_target"] = True
    problems = problems_of(with_graph({"kind": "k_nearest", "k": 1}, far))
    assert problems == [
        (
            "algorithm.graph",
            "is not connected: vehicles {0,1} and {2,3} are not connected (indices in "
            "vehicles:); the formation needs every vehicle linked to every other through "
            "neighbours",
        )
    ]


@pytest.mark.parametrize(
    "graph",
    [
        {"kind": "ring"},
        {"kind": "k_nearest", "k": 2},
        {"kind": "edges", "edges": [[0, 1], [1, 2], [2, 3]]},
        {"kind": "complete"},
    ],
)
def test_connected_graphs_load(graph):
    scenario = parse_scenario(yaml.safe_dump(with_graph(graph)), source="test.yaml")
    assert scenario.algorithm.graph.kind == graph["kind"]


def test_a_sparse_graph_with_the_separation_guard_is_refused():
    data = with_graph({"kind": "ring"})
    data["safety"] = {"min_separation_m": 0.5}
    problems = problems_of(data)
    assert any(
        where == "algorithm.graph" and "separation guard" in message for where, message in problems
    ), problems


def test_a_sparse_graph_flies():
    for graph in ({"kind": "ring"}, {"kind": "k_nearest", "k": 2}, {"kind": "complete"}):
        scenario = parse_scenario(yaml.safe_dump(with_graph(graph)), source="g.yaml")
        assert flight_problems(scenario) == [], graph


@pytest.mark.parametrize("kind", ["link_lost", "taken_over"])
def test_a_ring_with_a_vehicle_gone_silent_is_refused_for_flight_at_its_event(kind):
    data = with_graph({"kind": "ring"})
    data["events"] = [{"kind": "vehicle_lost", "vehicle": 2, "at_step": 5}]
    data["events"].append({"kind": kind, "vehicle": 3, "at_step": 10})
    problems = flight_problems(parse_scenario(yaml.safe_dump(data), source="ring.yaml"))
    assert [location for location, _ in problems] == ["events[1]"], problems
    assert "cannot be flown on a ring graph" in problems[0][1]
    data["algorithm"]["graph"] = {"kind": "k_nearest", "k": 2}
    assert flight_problems(parse_scenario(yaml.safe_dump(data), source="k.yaml")) == []


def test_the_default_graph_is_left_out_of_the_recorded_scenario():
    plain = parse_scenario((CONFIGS / "paper_tracking.yaml").read_text(), source="p.yaml")
    explicit = parse_scenario(yaml.safe_dump(with_graph({"kind": "complete"})), source="test.yaml")
    assert explicit == plain
    assert "graph" not in plain.model_dump(mode="json")["algorithm"]
    ring = parse_scenario(yaml.safe_dump(with_graph({"kind": "ring"})), source="test.yaml")
    assert ring.model_dump(mode="json")["algorithm"]["graph"]["kind"] == "ring"
    with pytest.raises(ConfigError):
        parse_scenario(yaml.safe_dump(with_graph({"kind": "edges"})), source="test.yaml")
