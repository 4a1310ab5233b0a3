"""The paper's pose fit: Levenberg–Marquardt on eq. (7), corrected (erratum 3; the cost and
its residual vector in costs.paper), minimised per hypothesis with
``scipy.optimize.least_squares(method="lm")`` from a start pose (the vision prior, or the
identity), as in §4.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from contactpose.costs.paper import eq7_residuals
from contactpose.progress import progress_bar


def fit_lm(obj_normals, obj_offsets, points, finger_normals, start):
    """LM fit of one hypothesis.

    obj_normals : (n, 3), obj_offsets : (n,), points, finger_normals : (n, 3),
    start : (4, 4) initial T_world_object.  ->  (T (4, 4), cost ℒ, converged bool)
    """
    from scipy.optimize import least_squares  # here: scipy.optimize takes 0.1 s to import

    x0 = np.concatenate([Rotation.from_matrix(start[:3, :3]).as_rotvec(), start[:3, 3]])
    sol = least_squares(eq7_residuals, x0, method="lm",
                        args=(obj_normals, obj_offsets, points, finger_normals))
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(sol.x[:3]).as_matrix()
    T[:3, 3] = sol.x[3:]
    return T, float(np.sum(sol.fun**2)), bool(sol.success)


def fit_lm_all(obj_normals, obj_offsets, points, finger_normals, start, *, deadline=None, progress=None):
    """fit_lm for H hypotheses. obj_normals : (H, n, 3), obj_offsets : (H, n), start : (4, 4).

    Returns T (H', 4, 4), cost (H',), converged (H',) bool: H' = H, or fewer when the
    deadline (progress.Deadline) passed first. progress : a bar (None: on a terminal).
    """
    out = []
    with progress_bar(total=len(obj_normals), desc="LM on eq. (7)", unit="hypothesis", show=progress) as bar:
        for nk, dk in zip(obj_normals, obj_offsets):
            if out and deadline is not None and deadline.passed:
                break
            out.append(fit_lm(nk, dk, points, finger_normals, start))
            bar.update()
    if not out:
        return np.empty((0, 4, 4)), np.empty(0), np.empty(0, bool)
    T, cost, ok = zip(*out)
    return np.array(T), np.array(cost), np.array(ok)
