"""SE(3) maps of geometry.se3 against GTSAM and finite differences."""

import gtsam
import numpy as np
import pytest

from contactpose.errors import ContactPoseError
from contactpose.geometry import se3


def test_se3_exp_log_match_gtsam():
    rng = np.random.default_rng(0)
    xi = rng.normal(size=(40, 6)) * np.r_[[0.8] * 3, [0.3] * 3]
    xi[:5] *= 1e-7  # the small-angle series
    xi[5, :3] = [np.pi - 1e-3, 0.0, 0.0]  # near π
    T = se3.exp(xi)
    for x, Ti in zip(xi, T):
        np.testing.assert_allclose(Ti, gtsam.Pose3.Expmap(x).matrix(), atol=1e-12)
        np.testing.assert_allclose(se3.log(Ti[None])[0], gtsam.Pose3.Logmap(gtsam.Pose3(Ti)), atol=1e-9)
    np.testing.assert_allclose(se3.log(T), xi, atol=1e-9)
    with pytest.raises(ContactPoseError, match=r"\(N, 6\)"):
        se3.exp(np.zeros((3, 5)))


def test_hat_is_the_cross_product_batched_and_compiled():
    rng = np.random.default_rng(1)
    v, u = rng.normal(size=(2, 7, 3))
    np.testing.assert_allclose(np.einsum("kij,kj->ki", se3.hat(v), u), np.cross(v, u), atol=1e-14)
    for a in v:
        np.testing.assert_array_equal(se3.hat3(a), se3.hat(a))


def test_retract_agrees_with_the_pose3_exponential_to_first_order():
    rng = np.random.default_rng(2)
    R = gtsam.Rot3.Expmap(rng.normal(size=3)).matrix()[None]
    t = rng.normal(size=(1, 3))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R[0], t[0]
    xi = rng.normal(size=6)
    for h in (1e-2, 1e-3):
        R2, t2 = se3.retract(R, t, h * xi[None])
        ref = T @ gtsam.Pose3.Expmap(h * xi).matrix()
        gap = max(np.abs(R2[0] - ref[:3, :3]).max(), np.abs(t2[0] - ref[:3, 3]).max())
        assert gap < 2 * h * h * (1 + np.abs(xi).max()) ** 2  # second order
    R2, t2 = se3.retract(R, t, np.r_[0, 0, 0, 1.0, 2.0, 3.0][None])  # a pure shift: in the object frame
    np.testing.assert_allclose(t2[0], t[0] + R[0] @ [1.0, 2.0, 3.0], atol=1e-14)


def test_inverse_of_a_rigid_transform():
    T = gtsam.Pose3(gtsam.Rot3.Expmap([0.3, -0.2, 1.1]), [0.1, 0.4, -2.0]).matrix()
    np.testing.assert_allclose(se3.inverse(T) @ T, np.eye(4), atol=1e-14)


def test_compiled_retraction_equals_the_numpy_one():
    rng = np.random.default_rng(3)
    for _ in range(20):
        R = gtsam.Rot3.Expmap(rng.normal(size=3)).matrix()
        t, xi = rng.normal(size=3), rng.normal(size=6) * np.r_[[0.7] * 3, [0.2] * 3]
        R1, t1 = se3.retract3(R, t, xi)
        R2, t2 = se3.retract(R[None], t[None], xi[None])
        np.testing.assert_allclose(R1, R2[0], atol=1e-14)
        np.testing.assert_allclose(t1, t2[0], atol=1e-14)
