"""``mission-runner replay``: the frames drawn from a run's recording, against the run itself."""

import csv
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from mission_runner.checks import validate_scenario
from mission_runner.cli import EXIT_BAD_INPUT, EXIT_OK, main
from mission_runner.errors import ReplayError
from mission_runner.outputs import write_results
from mission_runner.recording import PALETTE
from mission_runner.replay import GIF, Replay, frame_steps, load_track, write_replay
from mission_runner.sim.simulator import simulate

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
STEPS = 40


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A short run of the paper scenario, vehicle 4 lost at step 30, written as simulate does."""
    data = yaml.safe_load((CONFIGS / "paper_tracking.yaml").read_text())
    data["timing"]["steps"] = STEPS
    data["events"] = [{"kind": "vehicle_lost", "vehicle": 4, "at_step": 30}]
    scenario = validate_scenario(data, "short")
    out = tmp_path_factory.mktemp("short")
    write_results(simulate(scenario), out, figures=False)
    return out


@pytest.fixture(scope="module")
def result(run_dir):
    """The run itself (the simulator is deterministic)."""
    data = yaml.safe_load((CONFIGS / "paper_tracking.yaml").read_text())
    data["timing"]["steps"] = STEPS
    data["events"] = [{"kind": "vehicle_lost", "vehicle": 4, "at_step": 30}]
    return simulate(validate_scenario(data, "short"))


def timeseries(run_dir):
    return list(csv.DictReader((run_dir / "timeseries.csv").read_text().splitlines()))


def test_one_frame_per_chosen_step_and_always_the_last():
    assert frame_steps(40, 1) == list(range(41))
    assert frame_steps(40, 3) == [*range(0, 40, 3), 40]
    assert frame_steps(40, 40) == [0, 40]


def test_the_gif_has_one_frame_per_chosen_step(run_dir, tmp_path):
    files = write_replay(run_dir, gif=tmp_path / "every3.gif", every=3, mp4=False)
    assert files.frames == len(frame_steps(STEPS, 3)) == 15
    with Image.open(files.gif) as gif:
        assert gif.n_frames == files.frames
        assert gif.size == files.size_px
    assert not list(tmp_path.glob(".*.partial"))


def test_the_track_is_the_run(run_dir):
    track = load_track(run_dir)
    rows = timeseries(run_dir)
    assert track.steps == STEPS
    assert track.name == "paper_tracking"
    for k in (0, 17, STEPS):
        for index, vehicle in enumerate((1, 2, 3, 4)):
            expected = (float(rows[k][f"v{vehicle}_north_m"]), float(rows[k][f"v{vehicle}_east_m"]))
            assert track.positions_m[k, index] == pytest.approx(expected, abs=1e-6)
    assert track.live[29, 3] and not track.live[30, 3] and not track.live[STEPS, 3]
    assert track.states[35, 3] == "absent"


def test_a_frame_draws_every_vehicle_where_the_run_had_it(run_dir, result):
    track = load_track(run_dir)
    rows = timeseries(run_dir)
    replay = Replay(track, width_px=640)
    k = 17
    frame = np.asarray(replay.draw(k))
    height = frame.shape[0]
    for index, vehicle in enumerate((1, 2, 3, 4)):
        north, east = float(rows[k][f"v{vehicle}_north_m"]), float(rows[k][f"v{vehicle}_east_m"])
        x, y = replay.vehicles[index].get_data()
        assert (x[0], y[0]) == (pytest.approx(north, abs=1e-6), pytest.approx(east, abs=1e-6))
        # The marker's centre pixel has the vehicle's colour (drawn last, over everything).
        column, row = replay.axes.transData.transform((north, east))
        pixel = frame[round(height - row), round(column)]
        assert np.abs(pixel - np.array(PALETTE[index]) * 255).max() < 40, (vehicle, pixel)
    # Vehicle 1's estimates of the target and the others: its true position minus phat_1j.
    x, y = replay.estimates[0].get_data()
    phat = result.estimates_m[k, 0, [0, 2, 3, 4]]
    expected = result.positions_m[0, k, 0] - phat
    assert np.allclose(np.stack([x, y], axis=-1), expected, atol=1e-6)


def test_replay_command_and_replay_flag(run_dir, tmp_path, capsys):
    assert main(["replay", str(run_dir), "--every", "10", "--no-mp4"]) == EXIT_OK
    assert "replay: 5 frames" in capsys.readouterr().out
    assert (run_dir / GIF).exists()
    out = tmp_path / "simulated"
    data = yaml.safe_load((CONFIGS / "paper_tracking.yaml").read_text())
    data["timing"]["steps"] = 12
    data["expect"] = {}
    config = tmp_path / "short.yaml"
    config.write_text(yaml.safe_dump(data))
    code = main(["simulate", str(config), "--out", str(out), "--no-figures", "--replay"])
    assert code == EXIT_OK
    with Image.open(out / GIF) as gif:
        assert gif.n_frames == 13


def test_a_folder_without_a_recording_is_bad_input(tmp_path, capsys):
    with pytest.raises(ReplayError, match=r"recording\.mcap not found"):
        load_track(tmp_path)
    assert main(["replay", str(tmp_path)]) == EXIT_BAD_INPUT
    assert "recording.mcap not found" in capsys.readouterr().err


@pytest.mark.skipif(shutil.which("ffmpeg") is None, reason="no ffmpeg on the PATH")
def test_an_mp4_beside_the_gif_where_ffmpeg_exists(run_dir, tmp_path):
    files = write_replay(run_dir, gif=tmp_path / "replay.gif", every=5)
    assert files.mp4 is not None and files.mp4.stat().st_size > 0


def test_a_folder_from_before_recordings_replays_from_its_tables(run_dir, tmp_path):
    """timeseries.csv and summary.json alone: the same positions, membership, circle and slots
    (no estimates, no controller states)."""
    old = tmp_path / "old"
    old.mkdir()
    for name in ("timeseries.csv", "summary.json"):
        shutil.copy(run_dir / name, old / name)
    recorded, tabled = load_track(run_dir), load_track(old)
    assert tabled.name == recorded.name
    assert np.allclose(tabled.positions_m, recorded.positions_m, atol=1e-6)
    assert np.array_equal(tabled.live, recorded.live)
    assert np.allclose(tabled.circle_m, recorded.circle_m, atol=1e-6)
    slots = np.isfinite(recorded.slots_m)
    assert np.allclose(tabled.slots_m[slots], recorded.slots_m[slots], atol=1e-6)
    assert np.isnan(tabled.estimates_m).all()
    assert write_replay(old, every=20, mp4=False).frames == 3
