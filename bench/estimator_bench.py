"""Relative-localization estimators on the paper's tracking scenario. Prints figures; asserts
nothing.

    python bench/estimator_bench.py            # 100 runs per setting
    python bench/estimator_bench.py --runs 20  # quicker
    python bench/estimator_bench.py --models-only  # the range models' table only (3 min)

First the range models (``MODELS``: independent ends as before, one exchange per pair, the UWB
model with pair bias and multipath per pair and per direction, with NLOS bursts): the filter,
its floor, shared ranges and the RLSE at beta_f 0.98, with the NLOS ranges read and the good
ranges gated. Then, on the default model, the tables below.

For each noise level (range std / per-step displacement std): the paper's RLSE (beta_f = 0.7),
the RLSE at its best forgetting factor (of a grid), the filter (``algorithm.estimator: ekf``) and
the floor; each as the median and p95 over runs of the per-edge RMS error over the last quarter,
and of the tail tracking RMS; then the RLSE (paper's and best beta_f) and the filter with shared
ranges (``algorithm.shared_ranges``: each pair from the mean of both ends' ranges). Then the
filter with 5 % NLOS outliers, with and without its gate, and the noise-free convergence.

The floor is the same filter started at the truth but claiming to know nothing of it (estimate
p_ij(0), covariance 1 m^2, no gate) on the trajectories the filter's closed loop flew, with fresh
measurements of the same noise model: every error it makes comes from the measurements, none
from a start-up far from the truth (no hand-over, no linearisation error while converging). It is
a reference, not a proof of optimality (a Cramer-Rao bound would be one).
"""

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mission_runner.checks import load_scenario, validate_scenario  # noqa: E402
from mission_runner.enclosing.ekf import FilterEdges, filter_update  # noqa: E402
from mission_runner.metrics import (  # noqa: E402
    SimulationResult,
    edge_rms,
    run_metrics,
)
from mission_runner.sensors import UwbRanging, odometry_error_step, range_readings  # noqa: E402
from mission_runner.sim.simulator import simulate  # noqa: E402
from mission_runner.wiring import filter_settings  # noqa: E402

LEVELS = [(0.1, 0.005), (0.02, 0.005), (0.1, 0.0)]
GRID = (0.9, 0.95, 0.98, 0.99, 0.995)


def scenario(
    range_std, displacement_std, estimator="rlse", forgetting=0.7, *, shared=False, **extra
):
    data = load_scenario(ROOT / "configs" / "paper_tracking.yaml").model_dump(mode="json")
    data["sensors"] = {
        "range_noise_std_m": range_std,
        "displacement_noise_std_m": displacement_std,
        **extra.pop("sensors", {}),
    }
    data["algorithm"]["estimator"] = estimator
    data["algorithm"]["forgetting_factor"] = forgetting
    data["algorithm"]["estimator_settings"] = extra
    data["algorithm"]["shared_ranges"] = shared
    data["expect"] = {}
    return validate_scenario(data)


def figures(result):
    """(per-edge median, p95, tracking median, p95, gated median) over the batch."""
    metrics = run_metrics(result)
    edge, track = metrics["tail_localization_error_rms_m"], metrics["tail_tracking_error_rms_m"]
    return (
        np.median(edge),
        np.percentile(edge, 95),
        np.median(track),
        np.percentile(track, 95),
        np.median(metrics["gated_ranges"]),
    )


#: The range models the table compares, at 0.1 m of timestamp noise and 5 mm of displacement
#: noise: as the simulator drew ranges before (independent at each end), one exchange per pair
#: with white noise only, and the UWB reference model (pair bias 5 cm, multipath 5 cm with 2 s
#: correlation; docs/algorithm.md, "The range model"), without and with 5 % NLOS in 2 s bursts.
UWB = {"range_bias_std_m": 0.05, "range_multipath_std_m": 0.05}
NLOS = {"range_outlier_probability": 0.05, "range_nlos_duration_s": 2.0}
MODELS = [
    ("independent ends (before)", {"range_scheme": "one_exchange_per_direction"}),
    ("one exchange per pair", {}),
    ("UWB: + bias, multipath", UWB),
    ("UWB, per direction", {**UWB, "range_scheme": "one_exchange_per_direction"}),
    ("UWB + 5 % NLOS bursts", {**UWB, **NLOS}),
]


def model_row(name, result):
    """One line of the model table: :func:`figures` plus NLOS ranges injected and the gate's
    false rejections (good ranges gated), medians over runs."""
    edge_median, edge_p95, track_median, track_p95, gated = figures(result)
    injected = np.median(result.nlos_ranges.sum(axis=-1))
    false = np.median(result.false_rejections.sum(axis=-1))
    print(
        f"  {name:<34} per edge {edge_median:.4f} / {edge_p95:.4f} m   "
        f"tracking {track_median:.4f} / {track_p95:.4f} m   gated {gated:.0f} "
        f"(NLOS read {injected:.0f}, good gated {false:.0f})"
    )
    return edge_median, edge_p95


def model_table(runs):
    """Each range model at 0.1 m / 5 mm: the filter, with shared ranges, its floor and the RLSE
    at beta_f 0.98."""
    print(f"\nrange models at 0.1 m / 5 mm, {runs} runs: median / p95 over runs of tail RMS")
    for model, sensors in MODELS:
        print(f"{model}")
        result = simulate(scenario(0.1, 0.005, "ekf", sensors=dict(sensors)), runs)
        edge_median, edge_p95 = model_row("filter (ekf)", result)
        floor_median, floor_p95 = floor(result)
        print(
            f"  {'floor (filter from truth)':<34} per edge {floor_median:.4f} / {floor_p95:.4f} m"
            f"   filter / floor {edge_median / floor_median:.2f} (median), "
            f"{edge_p95 / floor_p95:.2f} (p95)"
        )
        shared = scenario(0.1, 0.005, "ekf", shared=True, sensors=dict(sensors))
        model_row("filter, shared ranges", simulate(shared, runs))
        rlse = scenario(0.1, 0.005, forgetting=0.98, sensors=dict(sensors))
        model_row("RLSE beta_f 0.98", simulate(rlse, runs))


def floor(result: SimulationResult, seed=7):
    """Per-edge tail RMS (median and p95 over runs) of the filter started at the truth (with a
    covariance of 1 m^2) on the flown trajectories of ``result``, with fresh measurements of its
    sensor model (gated only if the model has NLOS)."""
    scenario_ = result.scenario
    # No gate (it could only reject good ranges), unless the model reads NLOS ranges.
    nlos = scenario_.sensors.range_outlier_probability > 0
    settings = filter_settings(scenario_)
    settings = settings if nlos else dataclasses.replace(settings, gate_chi2=None)
    positions, target = result.positions_m, result.target_m  # (B, K+1, N, 2), (K+1, 2)
    runs, steps = positions.shape[0], positions.shape[1] - 1
    n = positions.shape[2]
    rng = np.random.default_rng(seed)
    senses = np.array([v.senses_target for v in scenario_.vehicles])
    edge = np.concatenate([senses[:, None], ~np.eye(n, dtype=bool)], axis=1)  # (N, N+1)
    edge = np.broadcast_to(edge, (runs, n, n + 1))

    def relative(k):
        everyone = np.concatenate([np.broadcast_to(target[k], (runs, 1, 2)), positions[:, k]], 1)
        return positions[:, k, :, None, :] - everyone[:, None, :, :]  # (B, N, N+1, 2)

    start = relative(0)
    edges = FilterEdges.initial((runs, n, n + 1))
    exact = dataclasses.replace(
        edges.filter,
        estimate_north_m=start[..., 0],
        estimate_east_m=start[..., 1],
        gain_nn=np.ones(edge.shape),
        gain_ee=np.ones(edge.shape),
        anchor_range_m=np.where(edge, np.linalg.norm(start, axis=-1), np.nan),
    )
    edges = dataclasses.replace(edges, filter=exact, engaged=edge.copy())
    odometry_error = np.zeros((runs, n, 2))
    squares = []
    uwb = UwbRanging(scenario_.sensors, n, scenario_.timing.step_s, batch=(runs,))
    for k in range(1, steps):
        truth = relative(k)
        true_m = np.linalg.norm(truth, axis=-1)
        ranges = np.concatenate(
            [
                range_readings(true_m[..., :1], scenario_.sensors, rng, measured=edge[..., :1]),
                uwb.read(true_m[..., 1:], rng, k=k),
            ],
            axis=-1,
        )
        odometry = np.concatenate(
            [
                np.broadcast_to(target[k] - target[0], (runs, 1, 2)),
                positions[:, k] - positions[:, 0] + odometry_error,
            ],
            axis=1,
        )
        rel = odometry[:, 1:, None, :] - odometry[:, None, :, :]
        edges, _ = filter_update(edges, ranges, rel[..., 0], rel[..., 1], step=k, settings=settings)
        north, east = edges.current(rel[..., 0], rel[..., 1])
        error = np.hypot(north - truth[..., 0], east - truth[..., 1])
        squares.append(edge_rms(np.where(edge, error, np.nan)) ** 2)
        odometry_error = odometry_error_step(scenario_.sensors, rng, odometry_error)
    tail = np.sqrt(np.mean(np.array(squares)[-(steps + 1) // 4 :], axis=0))
    return np.median(tail), np.percentile(tail, 95)


def row(name, values):
    edge_median, edge_p95, track_median, track_p95, gated = values
    print(
        f"  {name:<26} per edge {edge_median:.4f} / {edge_p95:.4f} m   "
        f"tracking {track_median:.4f} / {track_p95:.4f} m   gated {gated:.0f}"
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument(
        "--models-only", action="store_true", help="only the range models' table (first part)"
    )
    arguments = parser.parse_args()
    runs = arguments.runs
    started = time.perf_counter()
    model_table(runs)
    if arguments.models_only:
        print(f"\n{time.perf_counter() - started:.0f} s")
        return
    print(f"paper tracking scenario, {runs} runs each; median / p95 over runs of tail RMS")
    for range_std, displacement_std in LEVELS:
        print(f"\nrange noise {range_std} m, displacement noise {displacement_std} m per step")
        row(
            "RLSE beta_f 0.7 (paper)",
            figures(simulate(scenario(range_std, displacement_std), runs)),
        )
        tuned = {
            beta: figures(simulate(scenario(range_std, displacement_std, forgetting=beta), runs))
            for beta in GRID
        }
        best = min(tuned, key=lambda beta: tuned[beta][0])
        row(f"RLSE beta_f {best} (best of grid)", tuned[best])
        result = simulate(scenario(range_std, displacement_std, "ekf"), runs)
        filtered = figures(result)
        row("filter (ekf)", filtered)
        floor_median, floor_p95 = floor(result)
        print(
            f"  {'floor (filter from truth)':<26} per edge {floor_median:.4f} / {floor_p95:.4f} m"
            f"   filter / floor {filtered[0] / floor_median:.2f} (median), "
            f"{filtered[1] / floor_p95:.2f} (p95)"
        )
        for name, setting in [
            ("RLSE beta_f 0.7, shared", scenario(range_std, displacement_std, shared=True)),
            (
                f"RLSE beta_f {best}, shared",
                scenario(range_std, displacement_std, forgetting=best, shared=True),
            ),
            ("filter, shared ranges", scenario(range_std, displacement_std, "ekf", shared=True)),
        ]:
            row(name, figures(simulate(setting, runs)))

    print("\nNLOS outliers (5 %, bias 0.3-3 m), range noise 0.1 m, displacement noise 0.005 m")
    for name, extra in [
        ("filter, gated", {}),
        ("filter, no gate", {"gate_chi2": None}),
        ("filter, shared, gated", {"shared": True}),
    ]:
        outlying = scenario(0.1, 0.005, "ekf", sensors={"range_outlier_probability": 0.05}, **extra)
        row(name, figures(simulate(outlying, runs)))
    paper = scenario(0.1, 0.005, forgetting=0.99, sensors={"range_outlier_probability": 0.05})
    row("RLSE beta_f 0.99", figures(simulate(paper, runs)))

    print("\nnoise-free: max relative-localization error over runs at step k")
    for name, setting in [
        ("RLSE beta_f 0.7", scenario(0, 0)),
        ("filter", scenario(0, 0, "ekf")),
        ("filter, shared", scenario(0, 0, "ekf", shared=True)),
    ]:
        error = simulate(setting, runs).localization_error_m
        steps = "  ".join(
            f"k={k}: {error[:, k].max():.1e} (median {np.median(error[:, k]):.1e})"
            for k in (45, 60, 80, 100)
        )
        print(f"  {name:<16} {steps}")
    print(f"\n{time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
