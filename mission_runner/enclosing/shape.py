"""Desired formation offsets: the circle of eq. ``desipos`` shaped by affine transforms.

r_i = A(k) [rho cos theta_i, rho sin theta_i, 1]^T with A = Translation @ Shearing @ Scaling (the
paper's remark after Lemma 1: scale first, then shear, then translate). The target's own offset
r_0 is always 0: a translation moves the circle away from the target, it does not move the target.
Offsets are planar, in the shared north-east orientation, in metres.
"""

import numpy as np
from numpy.typing import ArrayLike, NDArray


def affine_matrix(
    translate_m: ArrayLike, scale: ArrayLike, shear: ArrayLike
) -> NDArray[np.float64]:
    """Homogeneous 3x3 matrix T @ H @ S.

    translate_m: ``(..., 2)`` [T_x, T_y] in metres; scale: ``(..., 2)`` [S_x, S_y] (> 0);
    shear: ``(..., 2)`` [H_a, H_b]. Returns ``(..., 3, 3)``.
    """
    translate_m, scale, shear = np.broadcast_arrays(
        np.asarray(translate_m, float), np.asarray(scale, float), np.asarray(shear, float)
    )
    matrix = np.zeros((*translate_m.shape[:-1], 3, 3))
    # H @ S = [[S_x, H_a S_y], [H_b S_x, S_y]]; T adds the last column.
    matrix[..., 0, 0] = scale[..., 0]
    matrix[..., 0, 1] = shear[..., 0] * scale[..., 1]
    matrix[..., 1, 0] = shear[..., 1] * scale[..., 0]
    matrix[..., 1, 1] = scale[..., 1]
    matrix[..., 0, 2] = translate_m[..., 0]
    matrix[..., 1, 2] = translate_m[..., 1]
    matrix[..., 2, 2] = 1.0
    return matrix


IDENTITY = affine_matrix(np.zeros(2), np.ones(2), np.zeros(2))


def desired_offsets(
    phase_rad: NDArray[np.float64], radius_m: float, shape: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Desired offsets from the target, r = A [rho cos theta, rho sin theta, 1].

    phase_rad: ``(..., N)``; radius_m: scalar; shape: ``(..., 3, 3)`` broadcastable against the
    leading axes of ``phase_rad``. Returns ``(..., N, 2)`` in metres.
    """
    circle_n = radius_m * np.cos(phase_rad)
    circle_e = radius_m * np.sin(phase_rad)
    linear = shape[..., None, :2, :2]
    offset = shape[..., None, :2, 2]
    return linear[..., 0] * circle_n[..., None] + linear[..., 1] * circle_e[..., None] + offset
