"""A straightforward per-vehicle Python-loop implementation of the paper's equations.

This is the baseline the vectorised simulator is measured against: what one writes first,
looping over vehicles and their neighbours with small numpy vectors, as in the paper's
notation. It simulates the paper's tracking scenario (noise-free, complete graph) and returns
the positions so the benchmark can check both implementations fly the same trajectory.
"""

import math

import numpy as np


def simulate_loop(scenario):
    algorithm, timing = scenario.algorithm, scenario.timing
    step_s, steps = timing.step_s, timing.steps
    beta, u_bar, beta_f = algorithm.beta, algorithm.saturation_m_s, algorithm.forgetting_factor
    rho, omega = algorithm.radius_m, algorithm.omega_rad_s
    n = len(scenario.vehicles)
    velocity_0 = np.array(scenario.target.path.velocity_m_s)
    gains = [algorithm.coupling_gain] * (n - 1) + [algorithm.coupling_gain_last]

    position = [np.array(v.initial_position_m, dtype=float) for v in scenario.vehicles]
    theta = [v.initial_phase_rad for v in scenario.vehicles]
    senses = [v.senses_target for v in scenario.vehicles]
    target = np.array(scenario.target.path.start_m, dtype=float)
    # Neighbours of i: the other vehicles (1..n) and the target (0) if i senses it.
    neighbours = [
        ([0] if senses[i] else []) + [j + 1 for j in range(n) if j != i] for i in range(n)
    ]
    p_hat = [{j: np.zeros(2) for j in neighbours[i]} for i in range(n)]
    gamma = [{j: np.eye(2) for j in neighbours[i]} for i in range(n)]
    trajectory = [np.array(position)]
    previous = None
    for _k in range(steps):
        everyone = [target, *position]
        distance = [
            {j: np.linalg.norm(position[i] - everyone[j]) for j in neighbours[i]} for i in range(n)
        ]
        if previous is not None:
            last_distance, last_displacement = previous
            for i in range(n):
                for j in neighbours[i]:
                    v = last_displacement[i + 1] - last_displacement[j]
                    zeta = 0.5 * (distance[i][j] ** 2 - last_distance[i][j] ** 2 - v @ v)
                    eps = zeta - v @ p_hat[i][j]
                    g = gamma[i][j]
                    g = (g - np.outer(g @ v, v @ g) / (beta_f + v @ g @ v)) / beta_f
                    gamma[i][j] = g
                    p_hat[i][j] = p_hat[i][j] + v + g @ v * eps
        new_theta = []
        for i in range(n):
            coupling = 0.0
            for j in range(n):
                if j != i:
                    for order, gain in enumerate(gains, start=1):
                        coupling += gain / (n - 1) / order * math.sin(order * (theta[i] - theta[j]))
            new_theta.append(theta[i] + step_s * omega + step_s * coupling)
        r = [np.zeros(2)] + [rho * np.array([math.cos(t), math.sin(t)]) for t in theta]
        r_next = [rho * np.array([math.cos(t), math.sin(t)]) for t in new_theta]
        velocity = []
        for i in range(n):
            u_bar_i = np.zeros(2)
            for j in neighbours[i]:
                u_bar_i += (p_hat[i][j] - (r[i + 1] - r[j])) / len(neighbours[i])
            u_bar_i *= -beta
            saturated = u_bar_i * u_bar / max(u_bar, np.linalg.norm(u_bar_i))
            velocity.append(saturated + (r_next[i] - r[i + 1]) / step_s + velocity_0)
        displacement = [velocity_0 * step_s] + [step_s * u for u in velocity]
        position = [position[i] + displacement[i + 1] for i in range(n)]
        target = target + displacement[0]
        theta = new_theta
        previous = (distance, displacement)
        trajectory.append(np.array(position))
    return np.array(trajectory)
