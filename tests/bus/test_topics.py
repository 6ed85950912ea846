"""Topic layout and the MQTT topic-filter matcher."""

from __future__ import annotations

import paho.mqtt.client as paho
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from mission_runner.bus import (
    ParsedTopic,
    TopicError,
    TopicKind,
    Topics,
    topic_matches,
    validate_pattern,
    validate_topic,
)

TOPICS = Topics.for_mission("demo")


class TestLayout:
    def test_default_prefix_is_enclosing_mission(self) -> None:
        assert TOPICS.prefix == "enclosing/demo"

    @pytest.mark.parametrize(
        ("topic", "parsed"),
        [
            (TOPICS.step(3), ParsedTopic(TopicKind.STEP, 3)),
            (TOPICS.ranges(2), ParsedTopic(TopicKind.RANGES, 2)),
            (TOPICS.ranges(14), ParsedTopic(TopicKind.RANGES, 14)),
            (TOPICS.target(1), ParsedTopic(TopicKind.TARGET, 1)),
            (TOPICS.status(16), ParsedTopic(TopicKind.STATUS, 16)),
            (TOPICS.control(), ParsedTopic(TopicKind.CONTROL)),
        ],
    )
    def test_built_topics_parse_back(self, topic: str, parsed: ParsedTopic) -> None:
        assert TOPICS.parse(topic) == parsed

    def test_topic_strings_are_documented_layout(self) -> None:
        assert TOPICS.step(3) == "enclosing/demo/vehicle/3/step"
        assert TOPICS.ranges(2) == "enclosing/demo/vehicle/2/ranges"
        assert TOPICS.target(1) == "enclosing/demo/vehicle/1/target"
        assert TOPICS.status(4) == "enclosing/demo/vehicle/4/status"
        assert TOPICS.control() == "enclosing/demo/control"

    @pytest.mark.parametrize(
        ("pattern", "matching", "not_matching"),
        [
            (TOPICS.all_steps(), TOPICS.step(7), TOPICS.status(7)),
            (TOPICS.ranges(2), TOPICS.ranges(2), TOPICS.ranges(3)),
            (TOPICS.all_ranges(), TOPICS.ranges(3), TOPICS.step(3)),
            (TOPICS.all_targets(), TOPICS.target(5), TOPICS.step(5)),
            (TOPICS.all_status(), TOPICS.status(5), TOPICS.control()),
            (TOPICS.everything(), TOPICS.control(), "enclosing/other/control"),
        ],
    )
    def test_patterns_select_their_topics(
        self, pattern: str, matching: str, not_matching: str
    ) -> None:
        validate_pattern(pattern)
        assert topic_matches(pattern, matching)
        assert not topic_matches(pattern, not_matching)

    @given(st.integers(1, 10_000))
    def test_any_ids_round_trip(self, vehicle_id: int) -> None:
        assert TOPICS.parse(TOPICS.ranges(vehicle_id)) == ParsedTopic(TopicKind.RANGES, vehicle_id)
        assert TOPICS.parse(TOPICS.step(vehicle_id)).vehicle_id == vehicle_id

    @pytest.mark.parametrize(
        "topic",
        [
            "enclosing/other/vehicle/1/step",  # other mission
            "enclosing/demo/vehicle/0/step",  # 0 is the target, not a vehicle
            "enclosing/demo/vehicle/01/step",  # non-canonical id
            "enclosing/demo/vehicle/+1/step",
            "enclosing/demo/vehicle/x/step",
            "enclosing/demo/vehicle/1/speed",
            "enclosing/demo/vehicle/1/range",
            "enclosing/demo/vehicle/1/range/2",  # one topic per pair: no longer the layout
            "enclosing/demo/vehicle/1/ranges/2",
            "enclosing/demo/vehicle/1/step/extra",
            "enclosing/demo/control/now",
            "enclosing/demo",
            "enclosing/demo/",
        ],
    )
    def test_foreign_topics_are_rejected(self, topic: str) -> None:
        with pytest.raises(TopicError):
            TOPICS.parse(topic)

    @pytest.mark.parametrize("vehicle_id", [0, -1, True, 1.0, "1"])
    def test_bad_vehicle_ids_are_rejected(self, vehicle_id: object) -> None:
        with pytest.raises(TopicError, match="vehicle id"):
            TOPICS.step(vehicle_id)  # type: ignore[arg-type]

    @pytest.mark.parametrize("prefix", ["", "a/+/b", "a/#", "/a", "a/", "a//b", "$SYS/x"])
    def test_bad_prefixes_are_rejected(self, prefix: str) -> None:
        with pytest.raises(TopicError):
            Topics(prefix)

    @pytest.mark.parametrize("mission_id", ["", "a/b", "+", "#"])
    def test_bad_mission_ids_are_rejected(self, mission_id: str) -> None:
        with pytest.raises(TopicError, match="mission id"):
            Topics.for_mission(mission_id)

    def test_topic_error_is_a_value_error(self) -> None:
        with pytest.raises(ValueError, match="wildcard"):
            validate_topic("a/+")


class TestMatcher:
    @pytest.mark.parametrize(
        ("pattern", "topic", "expected"),
        [
            ("a/b", "a/b", True),
            ("a/+", "a/b", True),
            ("a/+", "a/b/c", False),
            ("a/+", "a", False),
            ("a/+", "a/", True),  # '+' matches an empty level
            ("a/#", "a", True),  # '#' also matches the parent level
            ("a/#", "a/b/c", True),
            ("#", "a/b", True),
            ("+/+", "/a", True),
            ("+", "/a", False),
            ("#", "$SYS/x", False),  # wildcards in the first level skip $ topics
            ("+/x", "$SYS/x", False),
            ("$SYS/#", "$SYS/x", True),
            ("A/b", "a/b", False),  # case-sensitive
        ],
    )
    def test_mqtt_spec_examples(self, pattern: str, topic: str, expected: bool) -> None:
        assert topic_matches(pattern, topic) is expected

    @pytest.mark.parametrize("pattern", ["a/#/b", "a/b#", "a+/b", "a/+b", "", "a\x00"])
    def test_malformed_patterns_are_rejected(self, pattern: str) -> None:
        with pytest.raises(TopicError):
            validate_pattern(pattern)

    @given(st.data())
    def test_agrees_with_paho(self, data: st.DataObject) -> None:
        # A small alphabet makes matches likely; paho's matcher is an independent oracle.
        level = st.sampled_from(["a", "b", "", "$x"])
        topic_levels = data.draw(st.lists(level, min_size=1, max_size=5))
        pattern_levels = [
            data.draw(st.sampled_from([text, "+", text, "a"])) for text in topic_levels
        ]
        pattern_levels = pattern_levels[: data.draw(st.integers(1, len(pattern_levels)))]
        if data.draw(st.booleans()):
            pattern_levels.append("#")
        topic = "/".join(topic_levels)
        pattern = "/".join(pattern_levels)
        assume(topic and pattern)  # empty strings are neither topics nor patterns
        validate_pattern(pattern)
        assert topic_matches(pattern, topic) == paho.topic_matches_sub(pattern, topic), (
            pattern,
            topic,
        )

    @given(st.lists(st.text(st.characters(exclude_characters="+#/\x00"), max_size=3), min_size=1))
    def test_every_topic_matches_itself_and_hash(self, levels: list[str]) -> None:
        topic = "/".join(levels)
        assume(topic)
        assert topic_matches(topic, topic)
        assert topic_matches("#", topic) is not topic.startswith("$")
