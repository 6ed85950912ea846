"""PX4 SITL per scenario vehicle (mission_runner.px4sitl): planning without PX4, and one start of
two real SIH instances when ``PX4_SITL_DIR`` points to a PX4 build."""

import argparse
import asyncio
import contextlib
import math
import os
import signal
import socket
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest
import yaml
from pymavlink.dialects.v20 import common as mavlink2

from mission_runner import px4sitl
from mission_runner.checks import validate_scenario
from mission_runner.config import Scenario
from mission_runner.px4sitl import (
    DEFAULT_NICE,
    EARTH_RADIUS_M,
    MAX_NICE,
    Px4BuildNotFoundError,
    Px4Instance,
    Px4SitlError,
    Px4SitlInstances,
    Px4SitlTimeoutError,
    add_arguments,
    api_port_of,
    check_instance_ids,
    instance_environment,
    instances_table,
    merged_params,
    offset_lat_lon_deg,
    plan_instances,
    px4_build_dir,
    px4_float,
    run_px4_sitl_command,
)
from mission_runner.runner.errors import RunnerError, RunnerTimeoutError

BASE_LAT_DEG, BASE_LON_DEG, BASE_ALT_M = 47.397742, 8.545594, 488.0


def scenario(
    ids: tuple[int, ...] = (7, 8),
    positions_m: tuple[tuple[float, float], ...] = ((-3.0, -2.0), (2.0, 4.0)),
    autopilot_params: dict[str, float | int] | None = None,
) -> Scenario:
    return validate_scenario(
        {
            "name": "px4sitl_test",
            "timing": {"step_s": 0.125, "steps": 10},
            "algorithm": {
                "beta": 1.0,
                "saturation_m_s": 0.4,
                "forgetting_factor": 0.7,
                "omega_rad_s": 0.5,
                "radius_m": 4.0,
            },
            "target": {"path": {"kind": "line", "start_m": [0.0, 0.0], "velocity_m_s": [0.0, 0.0]}},
            "vehicles": [
                {
                    "id": vehicle_id,
                    "initial_position_m": list(position_m),
                    "initial_phase_rad": 0.0,
                    "senses_target": index == 0,
                }
                for index, (vehicle_id, position_m) in enumerate(zip(ids, positions_m, strict=True))
            ],
            "flight": {"autopilot_params": autopilot_params or {}},
        }
    )


def fake_build(root: Path) -> Path:
    """A directory shaped like a PX4 checkout with build/px4_sitl_default (never executed)."""
    build = root / "build" / "px4_sitl_default"
    (build / "bin").mkdir(parents=True)
    (build / "etc").mkdir()
    (build / "bin" / "px4").write_text("#!/bin/sh\nexit 1\n")
    return build


# --- ids and instances ----------------------------------------------------------------------


def test_ids_that_are_instance_plus_one_are_accepted() -> None:
    check_instance_ids([7, 8], 6)
    check_instance_ids([1, 2, 3, 4], 0)


def test_consecutive_ids_off_by_some_instances_suggest_the_first_instance() -> None:
    with pytest.raises(
        Px4SitlError, match=r"\[7, 8\].*instances 0\.\.1.*need ids \[1, 2\].*--first-instance 6"
    ):
        check_instance_ids([7, 8], 0)


def test_ids_that_are_not_consecutive_must_be_renumbered() -> None:
    with pytest.raises(Px4SitlError, match=r"\[1, 3\].*renumber"):
        check_instance_ids([1, 3], 0)
    with pytest.raises(Px4SitlError, match=r"\[2, 1\].*renumber"):
        check_instance_ids([2, 1], 0)


def test_a_negative_first_instance_is_refused() -> None:
    with pytest.raises(Px4SitlError, match=">= 0"):
        check_instance_ids([1], -1)


def test_the_check_runs_before_anything_starts(tmp_path: Path) -> None:
    fake_build(tmp_path)
    with pytest.raises(Px4SitlError, match="--first-instance 6"):
        Px4SitlInstances(scenario(), tmp_path, first_instance=0)


def test_ports_follow_px4s_layout_including_the_shared_api_port_above_nine(
    tmp_path: Path,
) -> None:
    instance = Px4Instance(7, 6, BASE_LAT_DEG, BASE_LON_DEG, BASE_ALT_M, tmp_path)
    assert (instance.sysid, instance.api_port, instance.gcs_port, instance.truth_port) == (
        7,
        14546,
        18576,
        19416,
    )
    assert instance.api_url == "udpin://0.0.0.0:14546"
    assert instance.log_path == tmp_path / "px4_console.log"
    assert instance.log_path.name != "log"  # PX4 needs ./log as a directory
    assert [api_port_of(i) for i in (0, 9, 10, 15)] == [14540, 14549, 14549, 14549]


def test_instances_above_nine_are_warned_about(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    fake_build(tmp_path)
    with caplog.at_level("WARNING", logger="mission_runner.px4sitl"):
        Px4SitlInstances(scenario(ids=(10, 11)), tmp_path, first_instance=9)
    assert "14549" in caplog.text


# --- placement --------------------------------------------------------------------------------


def test_homes_sit_at_the_initial_positions_around_the_base_home(tmp_path: Path) -> None:
    planned = plan_instances(
        scenario(),
        tmp_path,
        first_instance=6,
        home_lat_deg=BASE_LAT_DEG,
        home_lon_deg=BASE_LON_DEG,
        home_alt_m=BASE_ALT_M,
    )
    assert [(p.vehicle_id, p.instance) for p in planned] == [(7, 6), (8, 7)]
    assert [p.work_dir for p in planned] == [tmp_path / "instance-6", tmp_path / "instance-7"]
    for item, (north_m, east_m) in zip(planned, [(-3.0, -2.0), (2.0, 4.0)], strict=True):
        # Back to metres the way the runner converts GPS fixes (runner/ranges.py).
        north_back_m = math.radians(item.home_lat_deg - BASE_LAT_DEG) * EARTH_RADIUS_M
        east_back_m = (
            math.radians(item.home_lon_deg - BASE_LON_DEG)
            * EARTH_RADIUS_M
            * math.cos(math.radians(BASE_LAT_DEG))
        )
        # PX4 holds the home in float32: half a step is 0.21 m of latitude, 0.04 m of longitude.
        assert north_back_m == pytest.approx(north_m, abs=0.22)
        assert east_back_m == pytest.approx(east_m, abs=0.04)
        assert item.placement_error_m == pytest.approx(
            math.hypot(north_back_m - north_m, east_back_m - east_m), abs=1e-6
        )
        assert item.home_lat_deg == px4_float(item.home_lat_deg)
        assert item.home_alt_m == BASE_ALT_M


def test_px4_float_rounds_to_float32_steps() -> None:
    assert px4_float(0.1) != 0.1
    assert px4_float(0.1) == pytest.approx(0.1, rel=1e-7)
    assert px4_float(px4_float(47.3977)) == px4_float(47.3977)
    step_deg = px4_float(47.397742 + 2**-19) - px4_float(47.397742 - 2**-19)
    assert step_deg in (2**-18, 0.0, 2 * 2**-18)
    assert math.radians(2**-18) * EARTH_RADIUS_M == pytest.approx(0.424, abs=0.001)


def test_one_metre_north_and_east_in_degrees() -> None:
    lat_deg, lon_deg = offset_lat_lon_deg(0.0, 0.0, 1.0, 1.0)
    assert lat_deg == pytest.approx(1 / 111_194.9, rel=1e-5)
    assert lon_deg == pytest.approx(1 / 111_194.9, rel=1e-5)
    lat_deg, lon_deg = offset_lat_lon_deg(60.0, 10.0, 0.0, 1.0)
    assert lat_deg == 60.0
    assert lon_deg - 10.0 == pytest.approx(2 / 111_194.9, rel=1e-5)  # cos 60 = 1/2


# --- environment ----------------------------------------------------------------------------


def test_environment_sets_airframe_home_speed_and_params_and_drops_inherited_px4_variables(
    tmp_path: Path,
) -> None:
    instance = Px4Instance(7, 6, 47.5, 8.5, 488.0, tmp_path)
    environment = instance_environment(
        instance,
        speed_factor=2.0,
        params={"MPC_ACC_HOR": 5.0, "COM_OBL_RC_ACT": 2, "NAV_DLL_ACT": 0},
        base_environment={"PATH": "/usr/bin", "PX4_PARAM_SDLOG_MODE": "-1", "PX4_SIM_MODEL": "x"},
    )
    assert environment == {
        "PATH": "/usr/bin",
        "PX4_SYS_AUTOSTART": "10040",
        "PX4_SIM_MODEL": "sihsim_quadx",
        "PX4_HOME_LAT": "47.500000000",
        "PX4_HOME_LON": "8.500000000",
        "PX4_HOME_ALT": "488.000",
        "PX4_SIM_SPEED_FACTOR": "2",
        "PX4_PARAM_MPC_ACC_HOR": "5.0",
        "PX4_PARAM_COM_OBL_RC_ACT": "2",
        "PX4_PARAM_NAV_DLL_ACT": "0",
    }


def test_speed_factor_one_leaves_px4s_timeouts_alone(tmp_path: Path) -> None:
    instance = Px4Instance(1, 0, 47.5, 8.5, 488.0, tmp_path)
    assert "PX4_SIM_SPEED_FACTOR" not in instance_environment(instance, base_environment={})


def test_given_params_override_the_scenarios_autopilot_params() -> None:
    merged = merged_params(
        scenario(autopilot_params={"MPC_ACC_HOR": 5.0, "MIS_TAKEOFF_ALT": 3.0}),
        {"MPC_ACC_HOR": 4.0, "COM_OBL_RC_ACT": 1},
    )
    assert merged == {"MPC_ACC_HOR": 4.0, "MIS_TAKEOFF_ALT": 3.0, "COM_OBL_RC_ACT": 1}


@pytest.mark.parametrize(
    ("params", "problem"),
    [
        ({"mpc_acc_hor": 1.0}, "not a PX4 name"),
        ({"A=B": 1.0}, "not a PX4 name"),
        ({"WAY_TOO_LONG_PARAM_NAME": 1.0}, "not a PX4 name"),
        ({"MPC_ACC_HOR": math.nan}, "finite number"),
        ({"MPC_ACC_HOR": True}, "finite number"),
    ],
)
def test_bad_params_are_refused(params: dict[str, float], problem: str) -> None:
    with pytest.raises(Px4SitlError, match=problem):
        merged_params(scenario(), params)


def test_the_table_says_what_runs_where(tmp_path: Path) -> None:
    instance = Px4Instance(7, 6, 47.5, 8.5, 488.0, tmp_path, pid=4242, ready_after_s=3.9)
    table = instances_table([instance])
    assert "udpin://0.0.0.0:14546" in table
    assert "18576" in table
    assert "19416" in table
    assert "4242" in table
    assert "--id 7 --url udpin://0.0.0.0:14546" in table


# --- the build ------------------------------------------------------------------------------


def test_a_checkout_or_its_build_dir_is_accepted(tmp_path: Path) -> None:
    build = fake_build(tmp_path)
    assert px4_build_dir(tmp_path) == build.resolve()
    assert px4_build_dir(build) == build.resolve()


def test_a_missing_binary_says_what_to_build(tmp_path: Path) -> None:
    with pytest.raises(Px4BuildNotFoundError, match="make px4_sitl_default") as raised:
        px4_build_dir(tmp_path)
    assert isinstance(raised.value, RunnerError)
    with pytest.raises(Px4BuildNotFoundError):
        Px4SitlInstances(scenario(ids=(1, 2)), tmp_path)


def test_a_timeout_is_both_a_px4_and_a_runner_timeout_error() -> None:
    error = Px4SitlTimeoutError("PX4 instance 6 (vehicle 7) to print 'Ready for takeoff!'", 30.0)
    assert isinstance(error, Px4SitlError)
    assert isinstance(error, RunnerTimeoutError)
    assert str(error).startswith("timed out after 30 s waiting for PX4 instance 6")


def test_the_command_line_arguments() -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    arguments = parser.parse_args(
        ["s.yaml", "--px4-dir", "/px4", "--first-instance", "6", "--speed", "2", "--work-dir", "w"]
    )
    assert arguments.nice == DEFAULT_NICE
    assert arguments.config == Path("s.yaml")
    assert arguments.px4_dir == Path("/px4")
    assert (arguments.first_instance, arguments.speed) == (6, 2.0)
    assert arguments.work_dir == Path("w")
    assert callable(arguments.handler)
    with pytest.raises(SystemExit):
        parser.parse_args(["s.yaml", "--px4-dir", "/px4", "--speed", "0"])
    assert parser.parse_args(["s.yaml", "--px4-dir", "/px4", "--nice", "0"]).nice == 0
    assert arguments.realtime is False
    assert parser.parse_args(["s.yaml", "--px4-dir", "/px4", "--realtime"]).realtime is True
    for bad in ("-1", "20", "x"):
        with pytest.raises(SystemExit):
            parser.parse_args(["s.yaml", "--px4-dir", "/px4", "--nice", bad])


# --- a fake PX4 that never gets ready, or dies ------------------------------------------------


def script_build(root: Path, body: str) -> Path:
    """A "PX4" that runs ``body`` as a shell script (how start-up failures look to us)."""
    build = fake_build(root)
    binary = build / "bin" / "px4"
    binary.write_text("#!/bin/sh\n" + body)
    binary.chmod(0o755)
    return build


async def group_gone(pgid: int, timeout_s: float) -> bool:
    """Whether process group ``pgid`` has no running member within ``timeout_s``. Killed members
    stay zombies until init reaps them, which a container's init may do late or never: a
    zombie runs nothing, so it does not count."""
    loop = asyncio.get_running_loop()
    deadline_s = loop.time() + timeout_s
    while loop.time() < deadline_s:
        if not running_members(pgid):
            return True
        await asyncio.sleep(0.05)
    return False


def running_members(pgid: int) -> list[int]:
    """The pids of group ``pgid``'s members that are not zombies (from /proc)."""
    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:  # the process ended meanwhile
            continue
        # pid (comm) state ppid pgrp ...: comm may hold spaces and parentheses.
        state, _, group = text[text.rindex(")") + 2 :].split()[:3]
        if int(group) == pgid and state != "Z":
            members.append(int(stat.parent.name))
    return members


def process_gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


@pytest.mark.asyncio
async def test_an_instance_that_exits_during_start_up_is_reported_with_its_console(
    tmp_path: Path,
) -> None:
    build = script_build(tmp_path / "px4", 'echo "PX4 server already running for instance $2"\n')
    sitl = Px4SitlInstances(
        scenario(ids=(31, 32)),
        build,
        first_instance=30,
        work_dir=tmp_path / "work",
        ready_timeout_s=10.0,
    )
    with pytest.raises(Px4SitlError, match=r"exited with code 0 during start-up(.|\n)*already"):
        async with sitl:
            pass
    assert all(process_gone(instance.pid or 0) for instance in sitl.instances)


@pytest.mark.asyncio
async def test_a_start_that_times_out_stops_every_instance_it_started(tmp_path: Path) -> None:
    build = script_build(tmp_path / "px4", "echo booting\nexec sleep 60\n")
    sitl = Px4SitlInstances(scenario(ids=(31, 32)), build, first_instance=30, ready_timeout_s=0.5)
    with pytest.raises(Px4SitlTimeoutError, match=r"instance 30(.|\n)*booting"):
        async with sitl:
            pass
    assert len(sitl.instances) == 2
    assert all(process_gone(instance.pid or 0) for instance in sitl.instances)
    assert sitl.run_dir is not None
    assert not sitl.run_dir.exists()  # a temporary run directory goes with the instances


@pytest.mark.asyncio
async def test_the_command_stops_when_asked_during_start_up(tmp_path: Path) -> None:
    build = script_build(tmp_path / "px4", "exec sleep 60\n")
    lines: list[str] = []
    instances = await run_px4_sitl_command(
        scenario(ids=(31, 32)),
        build,
        first_instance=30,
        speed_factor=1.0,
        work_dir=tmp_path / "work",
        until=asyncio.sleep(0.3),
        report=lines.append,
    )
    assert instances == []
    assert lines == ["stopped before PX4 SITL was ready"]
    consoles = list((tmp_path / "work").glob("*/instance-*/px4_console.log"))
    assert len(consoles) == 2  # a given work dir is kept


@pytest.mark.asyncio
async def test_a_busy_port_is_named_before_px4_starts(tmp_path: Path) -> None:
    build = script_build(tmp_path / "px4", "exec sleep 60\n")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as holder:
        holder.bind(("127.0.0.1", 18570 + 31))
        sitl = Px4SitlInstances(scenario(ids=(31, 32)), build, first_instance=30)
        with pytest.raises(Px4SitlError, match=r"18601 \(GCS link\)(.|\n)*--first-instance"):
            async with sitl:
                pass
    assert len(sitl.instances) == 1  # instance 30 had started; it was stopped
    assert all(process_gone(instance.pid or 0) for instance in sitl.instances)


READY_THEN_SLEEP = 'echo $$ > pid\necho "INFO  [commander] Ready for takeoff!"\nexec sleep 60\n'


@pytest.mark.asyncio
async def test_an_unknown_parameter_is_named(tmp_path: Path) -> None:
    build = script_build(
        tmp_path / "px4",
        'echo "ERROR [param] Parameter MPC_ACC_HRZ not found."\n' + READY_THEN_SLEEP,
    )
    sitl = Px4SitlInstances(
        scenario(ids=(31, 32)), build, first_instance=30, params={"MPC_ACC_HRZ": 5.0}
    )
    with pytest.raises(Px4SitlError, match=r"no parameter.*MPC_ACC_HRZ"):
        async with sitl:
            pass
    assert all(process_gone(instance.pid or 0) for instance in sitl.instances)


@pytest.mark.asyncio
async def test_an_instance_that_dies_is_reported_and_the_others_fly_on(tmp_path: Path) -> None:
    """One PX4 crashing (or killed) must not take the swarm's other vehicles out of the air:
    it is reported at once, the others run until stopped, and the command fails in the end."""
    build = script_build(
        tmp_path / "px4",
        'echo $$ > pid\necho "Ready for takeoff!"\n'
        'if [ "$2" = 31 ]; then sleep 0.5; echo crashed; exit 3; fi\n'
        "exec sleep 60\n",
    )
    lines: list[str] = []
    reported, stop = asyncio.Event(), asyncio.Event()

    def report(line: str) -> None:
        lines.append(line)
        if "exited with code" in line:
            reported.set()

    async def survivor_then_stop() -> None:
        await reported.wait()
        pids = [int(path.read_text()) for path in (tmp_path / "work").glob("*/instance-*/pid")]
        assert sum(not process_gone(pid) for pid in pids) == 1  # instance 30 flies on
        stop.set()

    with pytest.raises(
        Px4SitlError, match=r"instance 31 \(vehicle 32\) exited with code 3(.|\n)*crashed"
    ):
        await asyncio.gather(
            survivor_then_stop(),
            run_px4_sitl_command(
                scenario(ids=(31, 32)),
                build,
                first_instance=30,
                work_dir=tmp_path / "work",
                until=stop.wait(),
                report=report,
            ),
        )
    assert "udpin://0.0.0.0:14549" in lines[0]
    assert any(line.startswith("error: PX4 instance 31 (vehicle 32) exited") for line in lines)
    assert lines[-1] == "stopping PX4 SITL"
    pids = [int(path.read_text()) for path in (tmp_path / "work").glob("*/instance-*/pid")]
    assert len(pids) == 2
    assert all(process_gone(pid) for pid in pids)


@pytest.mark.asyncio
@pytest.mark.parametrize("nice", [None, 0, 10])
async def test_instances_run_at_a_lower_cpu_priority_than_the_mission(
    tmp_path: Path, nice: int | None
) -> None:
    """Each instance (its process and, on Linux, its session's scheduling autogroup, which is
    what the kernel shares the CPU between) runs ``nice`` lower (by default not), so that where
    cores are short the simulation slows rather than the controllers missing deadlines."""
    build = script_build(
        tmp_path / "px4",
        "cut -d ' ' -f 19 /proc/self/stat > nice\n"
        "cat /proc/self/autogroup > autogroup 2>/dev/null\n"
        'echo "Ready for takeoff!"\nexec sleep 60\n',
    )
    read = asyncio.Event()
    found: dict[str, str] = {}

    async def look_then_stop() -> None:
        while not found:
            files = sorted((tmp_path / "work").glob("*/instance-*/nice"))
            if files and files[0].read_text().strip():
                found["nice"] = files[0].read_text().strip()
                autogroup = files[0].with_name("autogroup")
                found["autogroup"] = autogroup.read_text() if autogroup.exists() else ""
            await asyncio.sleep(0.05)
        read.set()

    options = {} if nice is None else {"nice": nice}
    await asyncio.gather(
        look_then_stop(),
        run_px4_sitl_command(
            scenario(ids=(31,), positions_m=((0.0, 0.0),)),
            build,
            first_instance=30,
            work_dir=tmp_path / "work",
            until=read.wait(),
            report=lambda line: None,
            **options,
        ),
    )
    lower = DEFAULT_NICE if nice is None else nice
    assert int(found["nice"]) == min(os.nice(0) + lower, MAX_NICE)
    if found["autogroup"]:  # Linux with autogroups
        assert found["autogroup"].strip().endswith(f"nice {lower}")


#: Prints whether the process may make itself real-time (as PX4 asks for its threads).
TRY_FIFO = (
    "import os\n"
    "try:\n"
    "    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))\n"
    "    print('real-time')\n"
    "except PermissionError:\n"
    "    print('refused')\n"
)


def may_be_real_time() -> bool:
    """Whether a process started here (no limits added) may make itself real-time: as root."""
    result = subprocess.run(
        [sys.executable, "-c", TRY_FIFO], capture_output=True, text=True, check=True
    )
    return result.stdout.strip() == "real-time"


@pytest.mark.asyncio
@pytest.mark.parametrize("realtime", [False, True])
async def test_instances_get_no_real_time_threads_unless_asked(
    tmp_path: Path, realtime: bool
) -> None:
    """As root, PX4's real-time threads would preempt every mission process on the machine:
    an instance may not make a thread real-time unless ``realtime``, as root too."""
    build = script_build(
        tmp_path / "px4",
        f"{sys.executable} -c \"$(cat <<'PY'\n{TRY_FIFO}PY\n)\" > fifo\n"
        'echo "Ready for takeoff!"\nexec sleep 60\n',
    )
    read = asyncio.Event()
    found: list[str] = []

    async def look_then_stop() -> None:
        while not found:
            files = sorted((tmp_path / "work").glob("*/instance-*/fifo"))
            if files and files[0].read_text().strip():
                found.append(files[0].read_text().strip())
            await asyncio.sleep(0.05)
        read.set()

    await asyncio.gather(
        look_then_stop(),
        run_px4_sitl_command(
            scenario(ids=(31,), positions_m=((0.0, 0.0),)),
            build,
            first_instance=30,
            work_dir=tmp_path / "work",
            until=read.wait(),
            report=lambda line: None,
            realtime=realtime,
        ),
    )
    expected = "real-time" if realtime and may_be_real_time() else "refused"
    assert found == [expected]


@pytest.mark.asyncio
async def test_a_failing_stop_condition_surfaces_and_stops_the_instances(tmp_path: Path) -> None:
    build = script_build(tmp_path / "px4", READY_THEN_SLEEP)

    lines: list[str] = []

    async def broken_stop() -> None:
        while not lines:  # until the instances are ready and reported
            await asyncio.sleep(0.05)
        raise OSError("signal source gone")

    with pytest.raises(OSError, match="signal source gone"):
        await run_px4_sitl_command(
            scenario(ids=(31, 32)),
            build,
            first_instance=30,
            work_dir=tmp_path / "work",
            until=broken_stop(),
            report=lines.append,
        )
    assert "udpin://0.0.0.0:14549" in lines[0]
    pids = [int(path.read_text()) for path in (tmp_path / "work").glob("*/instance-*/pid")]
    assert len(pids) == 2
    assert all(process_gone(pid) for pid in pids)


@pytest.mark.asyncio
async def test_an_instance_that_ignores_sigterm_is_killed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(px4sitl, "STOP_TIMEOUT_S", 0.5)
    build = script_build(
        tmp_path / "px4",
        "trap '' TERM\necho $$ > pid\necho 'Ready for takeoff!'\nwhile true; do sleep 0.1; done\n",
    )
    sitl = Px4SitlInstances(
        scenario(ids=(31,), positions_m=((0.0, 0.0),)), build, first_instance=30, work_dir=tmp_path
    )
    async with sitl:
        pid = sitl.instances[0].pid or 0
    assert process_gone(pid)
    assert await group_gone(pid, timeout_s=2.0)  # its sleeps went with it


def test_the_command_runs_until_sigterm_and_stops_the_instances(tmp_path: Path) -> None:
    build = script_build(tmp_path / "px4", READY_THEN_SLEEP)
    config = tmp_path / "scenario.yaml"
    config.write_text(
        yaml.safe_dump(scenario(ids=(31, 32)).model_dump(mode="json", exclude_defaults=True))
    )
    driver = (
        "import argparse, sys\n"
        "from mission_runner import px4sitl\n"
        "parser = argparse.ArgumentParser()\n"
        "px4sitl.add_arguments(parser)\n"
        "arguments = parser.parse_args()\n"
        "sys.exit(arguments.handler(arguments))\n"
    )
    work = tmp_path / "work"
    process = subprocess.Popen(
        [
            *(sys.executable, "-c", driver, str(config)),
            *("--px4-dir", str(build), "--first-instance", "30", "--work-dir", str(work)),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        output = []
        assert process.stdout is not None
        for line in process.stdout:
            output.append(line)
            if line.startswith("  mission-runner vehicle CONFIG --id 32"):
                break
        process.send_signal(signal.SIGTERM)
        rest, _ = process.communicate(timeout=20)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(timeout=5)
    text = "".join(output) + rest
    assert process.returncode == 0, text
    assert "stopping PX4 SITL" in text
    pids = [int(path.read_text()) for path in work.glob("*/instance-*/pid")]
    assert len(pids) == 2
    assert all(process_gone(pid) for pid in pids)


# --- real PX4 SITL ----------------------------------------------------------------------------


@pytest.fixture
def px4_dir() -> Iterator[Path]:
    location = os.environ.get("PX4_SITL_DIR")
    if not location:
        pytest.skip("set PX4_SITL_DIR to a PX4 checkout built with `make px4_sitl_default`")
    try:
        px4_build_dir(location)
    except Px4BuildNotFoundError as error:
        pytest.skip(f"PX4_SITL_DIR does not point to a PX4 SITL build: {error}")
    yield Path(location)


class _Collector(asyncio.DatagramProtocol):
    """MAVLink messages arriving on one UDP port, by type, from one system."""

    def __init__(self, sysid: int) -> None:
        self.sysid = sysid
        self.parser = mavlink2.MAVLink(None)
        self.parser.robust_parsing = True
        self.messages: dict[str, list[mavlink2.MAVLink_message]] = {}
        self.other_systems: set[tuple[int, str]] = set()
        self.changed = asyncio.Event()

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        for message in self.parser.parse_buffer(data) or []:
            # PX4's events (ids 410-411) are not in pymavlink's common dialect.
            if message.get_type() == "BAD_DATA" or message.get_type().startswith("UNKNOWN"):
                continue
            if message.get_srcSystem() != self.sysid:
                self.other_systems.add((message.get_srcSystem(), message.get_type()))
                continue
            self.messages.setdefault(message.get_type(), []).append(message)
        self.changed.set()

    async def wait_for(
        self, message_type: str, count: int, timeout_s: float
    ) -> list[mavlink2.MAVLink_message]:
        async with asyncio.timeout(timeout_s):
            while len(self.messages.get(message_type, [])) < count:
                self.changed.clear()
                await self.changed.wait()
        return self.messages[message_type][:count]


@contextlib.asynccontextmanager
async def listening(port: int, sysid: int) -> AsyncIterator[_Collector]:
    loop = asyncio.get_running_loop()
    transport, collector = await loop.create_datagram_endpoint(
        lambda: _Collector(sysid), local_addr=("127.0.0.1", port)
    )
    try:
        yield collector
    finally:
        transport.close()


def metres_between(lat1_deg: float, lon1_deg: float, lat2_deg: float, lon2_deg: float) -> float:
    north_m = math.radians(lat2_deg - lat1_deg) * EARTH_RADIUS_M
    east_m = math.radians(lon2_deg - lon1_deg) * EARTH_RADIUS_M * math.cos(math.radians(lat1_deg))
    return math.hypot(north_m, east_m)


@pytest.mark.px4
@pytest.mark.timeout(90)
@pytest.mark.asyncio
async def test_two_sih_instances_answer_as_their_vehicles_from_their_homes(
    px4_dir: Path, tmp_path: Path
) -> None:
    positions_m = ((-3.0, -2.0), (20.0, 40.0))
    sitl = Px4SitlInstances(
        scenario(ids=(7, 8), positions_m=positions_m, autopilot_params={"MPC_ACC_HOR": 5.0}),
        px4_dir,
        first_instance=6,
        work_dir=tmp_path / "work",
        ready_timeout_s=45.0,
    )
    async with sitl:
        instances = sitl.instances
        assert [(i.vehicle_id, i.instance, i.sysid) for i in instances] == [(7, 6, 7), (8, 7, 8)]
        for instance, (north_m, east_m) in zip(instances, positions_m, strict=True):
            assert instance.pid is not None
            assert instance.ready_after_s is not None
            assert instance.work_dir.parent == sitl.run_dir
            assert instance.log_path.is_file()
            assert (instance.work_dir / "log").is_dir()
            console = instance.log_path.read_text(errors="replace")
            assert "MPC_ACC_HOR: curr: 3.0000 -> new: 5.0000" in console
            # The API port is free for the mission runner once the context is entered.
            async with listening(instance.api_port, instance.sysid) as api:
                heartbeat = (await api.wait_for("HEARTBEAT", 1, timeout_s=5.0))[0]
                assert heartbeat.autopilot == mavlink2.MAV_AUTOPILOT_PX4
                assert heartbeat.type == mavlink2.MAV_TYPE_QUADROTOR
                positions = await api.wait_for("GLOBAL_POSITION_INT", 5, timeout_s=5.0)
            assert api.other_systems == set()
            expected_lat_deg, expected_lon_deg = offset_lat_lon_deg(
                BASE_LAT_DEG, BASE_LON_DEG, north_m, east_m
            )
            for position in positions:
                error_m = metres_between(
                    expected_lat_deg, expected_lon_deg, position.lat / 1e7, position.lon / 1e7
                )
                assert error_m < 1.0, f"vehicle {instance.vehicle_id} {error_m:.2f} m from home"
            async with listening(instance.truth_port, instance.sysid) as truth:
                state = (await truth.wait_for("HIL_STATE_QUATERNION", 1, timeout_s=5.0))[0]
            # SIH's truth sits on the home PX4 holds (float32-rounded), to GLOBAL_POSITION_INT's
            # 1e-7 deg.
            truth_error_m = metres_between(
                instance.home_lat_deg, instance.home_lon_deg, state.lat / 1e7, state.lon / 1e7
            )
            assert truth_error_m < 0.05
    pids = [instance.pid or 0 for instance in sitl.instances]
    assert all(process_gone(pid) for pid in pids)
    for pid in pids:
        assert await group_gone(pid, timeout_s=2.0)
    assert sitl.run_dir is not None
    assert sitl.run_dir.is_dir()  # a given work dir is kept, logs and all
