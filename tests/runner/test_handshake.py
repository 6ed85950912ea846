"""Getting a process ready for k = 0."""

import gc

from mission_runner.bus import ControlCommand, MissionControl
from mission_runner.runner.handshake import clock_change_problem, freeze_heap, take_clock_change
from mission_runner.runner.timesync import MissionTime


def test_what_lives_at_the_start_is_out_of_the_collectors_sight():
    """A vehicle process holds MAVSDK, numpy, pydantic and the bus: a full collection walked it
    all, 150 ms at a time in flight. After freeze_heap the oldest generation holds almost
    nothing, so collecting it costs nothing."""
    heap = [{"step": k, "ranges": [float(k)] * 3} for k in range(100_000)]
    try:
        freeze_heap()
        assert gc.get_freeze_count() >= 2 * len(heap)
        assert len(gc.get_objects(generation=2)) < 1_000
    finally:
        gc.unfreeze()
    assert len(gc.get_objects(generation=2)) >= 2 * len(heap)


def clock_command(rate, at_unix_s, mission_s):
    return MissionControl(
        ControlCommand.CLOCK, mission_s, clock_rate=rate, clock_reference_s=at_unix_s
    )


def test_a_clock_change_is_taken_only_where_it_keeps_the_clock_continuous():
    """A forged or misdirected change must not step every vehicle's clock (and its steps)."""
    time = MissionTime(unix=lambda: 1000.0)
    time.set(0.7, reference_s=990.0)
    at_s = 1000.5
    here_s = time.from_unix(at_s)
    assert take_clock_change(clock_command(1.0, at_s, here_s), time, unix_clock=lambda: 1000.0)
    assert time.latest_rate == 1.0
    far = clock_command(2.0, 1100.0, time.from_unix(1100.0))
    assert "takes effect +100.0 s" in clock_change_problem(far, time, 1000.0)
    jump = clock_command(2.0, 1001.0, time.from_unix(1001.0) + 30.0)
    assert "step this mission clock by +30.000 s" in clock_change_problem(jump, time, 1000.0)
    assert not take_clock_change(jump, time, unix_clock=lambda: 1000.0)
    bare = MissionControl(ControlCommand.CLOCK, here_s)
    assert "no clock_rate" in clock_change_problem(bare, time, 1000.0)
    assert time.latest_rate == 1.0
