"""The ceiling on strict top-1 (harness.ceiling) against known answers: on a box, every
placement that puts noise-free contacts on its faces fits exactly, so counted apart they
share the posterior evenly; a brute force over the box's 24 axis-aligned turns counts them."""

from __future__ import annotations

import numpy as np
import pytest

from contactpose.harness.ceiling import placement_fits, posteriors, truth_share
from contactpose.localize import localize
from contactpose.model.symmetry import Symmetry, symmetry
from contactpose.sim import grasps as simulate
from contactpose.sim.objects import make_box

HALF = np.array([0.10, 0.06, 0.04]) / 2  # sim.objects.make_box, centred at the origin

NOISE = dict(position_noise=1e-4, normal_noise_deg=0.5)


def test_posteriors_follow_the_likelihood_ratio():
    assert np.allclose(posteriors([3.0, 3.0, 3.0, 3.0]), 0.25)
    assert np.allclose(posteriors([1.0, 1.0 + 2 * np.log(3.0)]), [0.75, 0.25])
    assert np.allclose(posteriors([1e4, 1e4 + 2 * np.log(3.0)]), [0.75, 0.25])  # no underflow


def box_grasp(box_model, seed):
    """Noise-free contacts on the +x face (two), the +y and the +z face: a determined grasp."""
    normals = box_model.planes.normals
    faces = [np.flatnonzero(normals @ axis > 0.999) for axis in np.eye(3)]
    rng = np.random.default_rng(seed)
    facets = [rng.choice(faces[0]), rng.choice(faces[0]), rng.choice(faces[1]), rng.choice(faces[2])]
    return simulate.grasp(box_model, rng, facets=facets)


def exact_placements(contacts, rotation):
    """Brute force: the poses that put every noise-free contact on a face of the box (its point
    on the face's plane and within its extent, its outward normal the face's). Normals along
    three axes fix the rotation up to the box's axis turns: R = rotation Q, Q a signed
    permutation of det 1 (24); each gives y = Rᵀt by least squares. -> how many fit"""
    count = 0
    for perm in ((0, 1, 2), (1, 2, 0), (2, 0, 1), (0, 2, 1), (2, 1, 0), (1, 0, 2)):
        for signs in np.ndindex(2, 2, 2):
            Q = np.zeros((3, 3))
            Q[np.arange(3), perm] = np.where(np.array(signs), -1.0, 1.0)
            if np.linalg.det(Q) < 0:
                continue
            R = rotation @ Q
            normals, points = -contacts.finger_normals @ R, contacts.points @ R   # object frame, before t
            axis = np.argmax(np.abs(normals), axis=1)
            rows = np.arange(len(axis))
            side = np.sign(normals[rows, axis])
            A = np.zeros((len(axis), 3))
            A[rows, axis] = side                                       # side·y[axis] = side·p[axis] − half[axis]
            b = side * points[rows, axis] - HALF[axis]
            y = np.linalg.lstsq(A, b, rcond=None)[0]
            if np.allclose(A @ y, b, atol=1e-9) and np.all(np.abs(points - y) <= HALF + 1e-9):
                count += 1
    return count


@pytest.mark.parametrize("seed", [0, 1, 3])
def test_placements_that_fit_alike_share_the_posterior(box_model, seed):
    """Counted apart (a trivial group), the placements of noise-free contacts on a box each
    fit exactly: the search lists every one the brute force counts (the box's half turns of
    the truth among them), and the ceiling is one over their number. Modulo the box's group
    the half turns are the truth. The true placement's χ² is 0."""
    g = box_grasp(box_model, seed)
    assert np.allclose(box_model.vertices.min(axis=0), -HALF) and len(make_box().faces) == len(box_model.faces)
    assert len(symmetry(box_model).rotations) == 4
    count = exact_placements(g.contacts, g.pose[:3, :3])
    assert count >= 4
    trivial = Symmetry(np.eye(4)[None], np.zeros((0, 3)), np.zeros(3))
    apart = placement_fits(box_model, g.contacts, g.pose, group=trivial, **NOISE)
    assert apart.true_chi2 < 1e-8 and not apart.drifted
    assert len(apart.wrong_chi2) + 1 == count and np.all(apart.wrong_chi2 < 1e-8)
    assert apart.ceiling == pytest.approx(1.0 / count, abs=1e-6)
    assert apart.wrong_fits_better
    modulo = placement_fits(box_model, g.contacts, g.pose, **NOISE)
    assert len(modulo.wrong_chi2) + 1 == count // 4
    assert modulo.ceiling == pytest.approx(4.0 / count, abs=1e-6)


def test_a_shifted_truth_is_not_the_true_placement(box_model):
    """Told a truth moved by a tenth of the diameter, the surface fit from it slides back to
    the contacts' placement, which is not the true one: the true placement's χ² is then the
    χ² at the told pose, far above noise, and the found placements, now wrong, take the
    posterior."""
    g = box_grasp(box_model, 2)
    shifted = g.pose.copy()
    shifted[:3, 3] += 0.1 * box_model.diameter * np.array([0.0, 0.0, 1.0])
    fits = placement_fits(box_model, g.contacts, shifted, **NOISE)
    assert fits.drifted and not fits.best_right and fits.wrong_fits_better
    assert fits.true_chi2 > 1e4 and fits.posterior[0] < 1e-6


@pytest.mark.parametrize("seed", [0, 1, 7])
def test_the_truth_share_is_one_over_the_placements_that_fit(box_model, seed):
    """Noise-free contacts on a box: every placement the brute force counts fits exactly and
    is as wide (a turn of the box), so modulo its four rotations the truth holds 4 / count of
    the evidence, whether the answer lists the truth or the search had missed it (its own
    fit from the true pose joins the placements)."""
    g = box_grasp(box_model, seed)
    expected = 4.0 / exact_placements(g.contacts, g.pose[:3, :3])
    result = localize(box_model, g.contacts, **NOISE)
    assert truth_share(box_model, g.contacts, result, g.pose)[0] == pytest.approx(expected, abs=1e-6)
    group = symmetry(box_model)
    missed = [p for p in result.placements if group.errors(p.pose, g.pose)[0] > 5.0]
    assert len(missed) == len(result.placements) - 1
    result.placements = missed
    share, chi2 = truth_share(box_model, g.contacts, result, g.pose)
    assert share == pytest.approx(expected, abs=1e-6) and chi2 < 1e-8


def test_a_shifted_truth_holds_no_share(box_model):
    g = box_grasp(box_model, 2)
    shifted = g.pose.copy()
    shifted[:3, 3] += 0.1 * box_model.diameter * np.array([0.0, 0.0, 1.0])
    result = localize(box_model, g.contacts, **NOISE)
    share, chi2 = truth_share(box_model, g.contacts, result, shifted)
    assert share < 1e-6 and chi2 > 1e4
