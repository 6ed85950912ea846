"""The Foxglove layout: the bundled file is what the command prints, and every topic it shows is
one a recording has."""

import json
import re
from pathlib import Path

import yaml

from mission_runner.cli import EXIT_OK, main
from mission_runner.recording import RECORDING, read_recording

ROOT = Path(__file__).resolve().parents[1]
LAYOUT = ROOT / "docs" / "foxglove_layout.json"


def test_the_bundled_layout_is_what_the_command_prints(capsys):
    assert main(["layout", str(ROOT / "configs" / "paper_tracking.yaml")]) == EXIT_OK
    assert capsys.readouterr().out == LAYOUT.read_text(), (
        "docs/foxglove_layout.json is stale: mission-runner layout configs/paper_tracking.yaml "
        "--out docs/foxglove_layout.json"
    )


def test_every_topic_in_the_layout_is_recorded(tmp_path):
    # Which topics a recording has does not depend on its length: 40 steps, not 600.
    data = yaml.safe_load((ROOT / "configs" / "paper_tracking.yaml").read_text())
    data["timing"]["steps"] = 40
    data.pop("expect")
    config = tmp_path / "short.yaml"
    config.write_text(yaml.safe_dump(data))
    out = tmp_path / "run"
    assert main(["simulate", str(config), "--out", str(out), "--no-figures", "--quiet"]) == EXIT_OK
    recorded = {message.topic for message in read_recording(out / RECORDING)}
    text = LAYOUT.read_text()
    shown = set(re.findall(r'"(/[a-z0-9_/]+)(?:\.[a-z_]+)?"', text))
    assert shown >= {"/formation/scene", "/mission/metrics", "/mission/events"}
    assert shown <= recorded
    json.loads(text)
