"""Getting a process ready for k = 0."""

import gc

from mission_runner.runner.handshake import freeze_heap


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
