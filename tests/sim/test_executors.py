"""Sweeps on a Dask cluster: the same table as here, failures named, nothing left running."""

import dataclasses
import multiprocessing
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from distributed import LocalCluster
from distributed.core import Status

from mission_runner.checks import load_scenario, validate_scenario
from mission_runner.cli import EXIT_OK, EXIT_RUNTIME_FAILURE, main
from mission_runner.errors import ClusterError, RunError, SimulationError
from mission_runner.sim.executors import (
    LOCAL_CLUSTER_FROM_STEPS,
    DaskExecutor,
    InProcess,
    open_executor,
)
from mission_runner.sim.sweep import Axis, combinations, run_sweep, sweep_csv

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
AXES = [Axis("algorithm.forgetting_factor", (0.7, 0.9)), Axis("seed", (1, 2))]


def tiny(steps=20):
    data = load_scenario(CONFIGS / "paper_tracking.yaml").model_dump(mode="json")
    data["timing"]["steps"] = steps
    return validate_scenario(data)


@pytest.fixture(scope="module")
def cluster():
    """Two worker processes of one thread each, as a small real cluster would have."""
    with LocalCluster(
        n_workers=2, processes=True, threads_per_worker=1, dashboard_address=":0"
    ) as running:
        yield running


def free_port():
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.mark.slow
def test_a_sweep_on_a_cluster_is_the_sweep_run_here(cluster):
    found = combinations(tiny(), AXES, runs=3)
    here = run_sweep(found)
    progress = []
    with DaskExecutor(cluster.scheduler_address) as executor:
        there = run_sweep(found, executor, on_point=lambda done, total: progress.append(done))
    assert sweep_csv(there) == sweep_csv(here)
    for near, far in zip(here, there, strict=True):
        assert near.values == far.values
        for name, values in near.metrics.items():
            np.testing.assert_array_equal(far.metrics[name], values, err_msg=name)
    assert progress == [1, 2, 3, 4]


@pytest.mark.slow
def test_the_command_sends_its_combinations_to_the_address(cluster, tmp_path):
    config = tmp_path / "tiny.yaml"
    config.write_text(
        (CONFIGS / "paper_tracking.yaml").read_text().replace("steps: 600", "steps: 20")
    )
    sets = ["--set", "algorithm.forgetting_factor=0.7,0.9", "--set", "seed=1,2", "--runs", "2"]
    tables = []
    for where in ("none", cluster.scheduler_address):
        out = tmp_path / where.replace("/", "_").replace(":", "_")
        arguments = [*sets, "--cluster", where, "--no-figures", "--quiet", "--out", str(out)]
        assert main(["sweep", str(config), *arguments]) == EXIT_OK
        tables.append((out / "sweep.csv").read_bytes())
    assert tables[0] == tables[1]
    assert tables[0].count(b"\n") == 5


@pytest.mark.slow
def test_a_run_that_fails_on_a_worker_is_named_with_its_values_and_seed(cluster):
    found = combinations(tiny(), AXES, runs=2, source="tiny.yaml")
    found[3] = dataclasses.replace(found[3], runs=0)  # simulate() refuses zero runs
    with (
        DaskExecutor(cluster.scheduler_address) as executor,
        pytest.raises(RunError) as caught,
    ):
        run_sweep(found, executor)
    assert caught.value.run == "tiny.yaml with algorithm.forgetting_factor=0.9, seed=2 (seed 2)"
    assert isinstance(caught.value.error, SimulationError) and caught.value.bad_input
    assert "runs must be >= 1" in str(caught.value)


@pytest.mark.slow
def test_ctrl_c_cancels_the_runs_and_closes_the_cluster_it_started():
    before = set(multiprocessing.active_children())
    found = combinations(tiny(), AXES, runs=2)

    def interrupt(done, total):
        raise KeyboardInterrupt

    executor = DaskExecutor(None, workers=2)
    with pytest.raises(KeyboardInterrupt), executor:
        assert len(executor.cluster.workers) == 2
        run_sweep(found, executor, on_point=interrupt)
    assert executor.cluster.status == Status.closed
    assert set(multiprocessing.active_children()) <= before


def test_an_unreachable_scheduler_is_named_within_the_timeout():
    address = f"tcp://127.0.0.1:{free_port()}"
    with (
        pytest.raises(ClusterError, match=rf"no Dask scheduler answered at {address} within 1 s"),
        DaskExecutor(address, timeout_s=1.0),
    ):
        pass


def test_the_command_names_an_unreachable_scheduler(tmp_path, capsys):
    address = f"tcp://127.0.0.1:{free_port()}"
    config = tmp_path / "tiny.yaml"
    config.write_text((CONFIGS / "paper_tracking.yaml").read_text())
    arguments = ["--set", "seed=1,2", "--cluster", address, "--connect-timeout", "1"]
    arguments += ["--out", str(tmp_path / "out")]
    assert main(["sweep", str(config), *arguments, "--quiet"]) == EXIT_RUNTIME_FAILURE
    assert f"no Dask scheduler answered at {address}" in capsys.readouterr().err


def test_a_cluster_is_started_only_for_a_sweep_worth_it(monkeypatch):
    monkeypatch.setattr("os.cpu_count", lambda: 2)
    small = open_executor(None, None, steps=LOCAL_CLUSTER_FROM_STEPS - 1, runs=8)
    with small as executor:
        assert isinstance(executor, InProcess)
    big = open_executor(None, 2, steps=LOCAL_CLUSTER_FROM_STEPS, runs=8)
    assert isinstance(big, DaskExecutor) and big.address is None and big.workers == 2
    with open_executor(None, None, steps=10**6, runs=1) as executor:  # nothing to share out
        assert isinstance(executor, InProcess)
    with open_executor("none", None, steps=10**6, runs=8) as executor:
        assert isinstance(executor, InProcess)
    remote = open_executor("tcp://scheduler:8786", None, steps=1, runs=1)
    assert isinstance(remote, DaskExecutor) and remote.address == "tcp://scheduler:8786"


def test_a_sweep_here_does_not_import_dask():
    code = (
        "import sys; from mission_runner.cli import main; "
        "from mission_runner.sim import executors, sweep; "
        "print(sorted({'dask', 'distributed'} & set(sys.modules)))"
    )
    loaded = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout
    assert loaded.strip() == "[]"
