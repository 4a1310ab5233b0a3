"""Starts around a pose (solvers.surface.multistart_ends) against brute force and a known
answer: the least χ²_S of the surface fits from each start, the other ends that fit within
noise (multistart_poses' basins), and, from poses 5° off on the rock1k's
rough surface, the true placement's own fit (the surface fit from the true pose) where the
plain fit stops in a local minimum."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from contactpose import Contacts, ObjectModel, localize, stages
from contactpose.contacts import Tolerance
from contactpose.costs.association import nearest_fit_facets
from contactpose.costs.surface import surface_residuals
from contactpose.geometry.metrics import rotation_error_deg
from contactpose.geometry.sampling import perturb_normals
from contactpose.model.symmetry import symmetry
from contactpose.options import fit_threshold
from contactpose.progress import Deadline
from contactpose.sim import fingertip, objects
from contactpose.sim import grasps as simulate
from contactpose.solvers.surface import (
    MULTISTART_ROWS,
    MULTISTART_SHIFT_FRAC,
    MULTISTART_TURN_DEG,
    multistart_ends,
    multistart_poses,
    multistart_starts,
    surface_fit,
)

OFF_DEG = 5.0


@pytest.fixture(scope="module")
def rock1k():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ObjectModel.from_mesh(objects.load("rock1k"))


def grasps(model, count, seed):
    """Rounded fingertips (5 % of the diameter) on the rock1k, noise 0.25 % and 1°: (Contacts,
    true pose, a pose OFF_DEG from it) each."""
    rng = np.random.default_rng(seed)
    D = model.diameter
    out = []
    while len(out) < count:
        pose = simulate.random_pose(rng, max_translation=0.5 * D)
        got = fingertip.approach(model.vertices, model.faces, rng, 4, 0.05 * D, cone_deg=30.0, mode="cone")
        if not got.hit.all():
            continue
        R, t = pose[:3, :3], pose[:3, 3]
        points = got.points @ R.T + t + rng.normal(0.0, 0.0025 * D, got.points.shape)
        normals = perturb_normals(got.normals @ R.T, np.radians(1.0), rng)
        off = pose.copy()
        axis = rng.normal(size=3)
        off[:3, :3] = R @ Rotation.from_rotvec(np.radians(OFF_DEG) * axis / np.linalg.norm(axis)).as_matrix()
        out.append((Contacts(points, object_normals=normals), pose, off))
    return out


def least(ends):
    """The end of least χ²_S (the first on a tie), as multistart_poses keeps it."""
    return ends[int(np.argmin([got[5] for got in ends]))]


def fit_from(model, contacts, pose, tolerance, facets=None):
    start = nearest_fit_facets(model, contacts, pose, tolerance) if facets is None else facets
    return surface_fit(model, contacts, pose[:3, :3], pose[:3, 3], start, tolerance)


def test_the_starts_are_the_stated_turns_and_shifts():
    rng = np.random.default_rng(3)
    R, t, D = Rotation.random(random_state=4).as_matrix(), rng.normal(size=3), 0.2
    starts = multistart_starts(R, t, D)
    assert starts.shape == (12, 4, 4)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = R, t
    turns = [rotation_error_deg(s, pose) for s in starts]
    shifts = np.linalg.norm(starts[:, :3, 3] - t, axis=1)
    assert np.allclose(turns[:6], MULTISTART_TURN_DEG) and np.allclose(turns[6:], 0.0, atol=1e-6)
    assert np.allclose(shifts[:6], 0.0) and np.allclose(shifts[6:], MULTISTART_SHIFT_FRAC * D)
    # about and along the object frame's axes, each sign once
    axes = np.concatenate([np.eye(3), -np.eye(3)])
    got = Rotation.from_matrix(R.T @ starts[:6, :3, :3]).as_rotvec()
    assert np.allclose(got, np.radians(MULTISTART_TURN_DEG) * axes)
    assert np.allclose((starts[6:, :3, 3] - t) @ R, MULTISTART_SHIFT_FRAC * D * axes)


def test_multistart_is_the_best_of_the_fits_from_every_start(rock1k):
    """Brute force: the least χ²_S of surface_fit from the pose (walking from its facets) and
    from each start (walking from the nearest-fit facets there), never above the plain fit."""
    tolerance = Tolerance.from_noise(0.0025 * rock1k.diameter, 1.0)
    for contacts, _, off in grasps(rock1k, 3, seed=11):
        facets = nearest_fit_facets(rock1k, contacts, off, tolerance)
        plain = fit_from(rock1k, contacts, off, tolerance, facets)
        each = [plain[5]] + [fit_from(rock1k, contacts, s, tolerance)[5]
                             for s in multistart_starts(off[:3, :3], off[:3, 3], rock1k.diameter)]
        got = least(multistart_ends(rock1k, contacts, off[:3, :3], off[:3, 3], facets, tolerance))
        assert got[5] == pytest.approx(min(each), rel=1e-12)
        assert got[5] <= plain[5]


def test_multistart_reaches_the_true_placement_where_the_plain_fit_stops(rock1k):
    """From poses 5° off the truth on the rock1k's rough surface, the plain surface fit stops
    in a local minimum above the true placement's (the fit from the true pose) in some grasps
    (17 of 48). From the starts around the same pose the fit reaches that minimum or a lower
    one within 2° of it in more than half of those (10; in most others a lower minimum
    2.6-8° away)."""
    tolerance = Tolerance.from_noise(0.0025 * rock1k.diameter, 1.0)
    stuck = reached = 0
    for contacts, pose, off in [g for seed in (5, 6, 7) for g in grasps(rock1k, 16, seed)]:
        truth = fit_from(rock1k, contacts, pose, tolerance)
        plain = fit_from(rock1k, contacts, off, tolerance)
        if plain[5] <= truth[5] + 1.0:
            continue
        stuck += 1
        got = least(multistart_ends(rock1k, contacts, off[:3, :3], off[:3, 3],
                                    nearest_fit_facets(rock1k, contacts, off, tolerance), tolerance))
        a, b = np.eye(4), np.eye(4)
        a[:3, :3], b[:3, :3] = got[0], truth[0]
        reached += got[5] <= truth[5] + 1e-6 and rotation_error_deg(a, b) < 2.0
    assert stuck >= 10
    assert reached >= 0.5 * stuck


def test_the_basins_are_every_other_end_that_fits_within_noise(rock1k):
    """Brute force: the ends multistart_poses lists beside each row's least are exactly the
    other surface fits, from the row's pose and from each start, whose χ²_S is within
    fit_threshold; the least moves the row only where it lowers the row's χ²."""
    tolerance = Tolerance.from_noise(0.0025 * rock1k.diameter, 1.0)
    limit = fit_threshold(4)
    seen = 0
    for contacts, pose, _ in grasps(rock1k, 3, seed=21):
        arrays = localize(rock1k, contacts, position_noise=tolerance.position_noise, normal_noise_deg=1.0,
                          surface=True, keep="all", diagnose=False).hypotheses.arrays
        (rows, fit, _, _), (brows, bfit, bfacets, _) = multistart_poses(rock1k, contacts, arrays, tolerance)
        expected, lowered = [], []
        for r in np.flatnonzero(~arrays.fit.underdetermined)[:MULTISTART_ROWS]:
            R, t = arrays.fit.R[r], arrays.fit.t[r]
            ends = [surface_fit(rock1k, contacts, R, t, arrays.facets[r], tolerance)] + \
                [fit_from(rock1k, contacts, s, tolerance) for s in multistart_starts(R, t, rock1k.diameter)]
            chi2 = np.array([e[5] for e in ends])
            least = int(np.argmin(chi2))
            expected += [(r, c) for i, c in enumerate(chi2) if i != least and c <= limit]
            lowered += [r] if chi2[least] < arrays.chi2[r] else []
        got = sorted((int(r), float(np.sum(surface_residuals(rock1k, contacts, R, t, f, tolerance) ** 2)))
                     for r, R, t, f in zip(brows, bfit.R, bfit.t, bfacets))
        assert [r for r, _ in got] == sorted(r for r, _ in expected)
        assert np.allclose([c for _, c in got], [c for _, c in sorted(expected)], rtol=1e-9)
        assert sorted(rows.tolist()) == sorted(lowered)
        seen += len(got)
    assert seen > 0


def test_given_rows_are_fitted_from_their_starts_until_the_deadline(rock1k):
    """multistart_poses(rows=...): the rows given, not the best ones, each moved to its least
    end where that lowers its χ² (brute force as above); a passed deadline fits none."""
    tolerance = Tolerance.from_noise(0.0025 * rock1k.diameter, 1.0)
    contacts, _, _ = grasps(rock1k, 1, seed=23)[0]
    arrays = localize(rock1k, contacts, position_noise=tolerance.position_noise, normal_noise_deg=1.0,
                      surface=True, keep="all", diagnose=False).hypotheses.arrays
    given = np.flatnonzero(~arrays.fit.underdetermined)[[2, 4]]
    (rows, fit, _, _), _ = multistart_poses(rock1k, contacts, arrays, tolerance, rows=given)
    lowered = []
    for r in given:
        R, t = arrays.fit.R[r], arrays.fit.t[r]
        ends = [surface_fit(rock1k, contacts, R, t, arrays.facets[r], tolerance)] + \
            [fit_from(rock1k, contacts, s, tolerance) for s in multistart_starts(R, t, rock1k.diameter)]
        lowered += [r] if min(e[5] for e in ends) < arrays.chi2[r] else []
    assert sorted(rows.tolist()) == sorted(lowered)
    (rows, _, _, _), (brows, _, _, _) = multistart_poses(rock1k, contacts, arrays, tolerance, rows=given,
                                                        deadline=Deadline(0.0))
    assert len(rows) == 0 and len(brows) == 0


def test_the_other_placements_leaders_are_the_first_of_each_strict_group(rock1k):
    """stages._unstarted_placements against a pairwise brute force: of the determined rows
    within PLACEMENT_REACH times the fit threshold, in rank order, each row that no earlier
    leader is strictly alike (5°, 5 % of the diameter, modulo symmetry) leads; the leaders
    strictly alike a started pose are left out (the best's, and then the second's too)."""
    tolerance = Tolerance.from_noise(0.0025 * rock1k.diameter, 1.0)
    group = symmetry(rock1k)
    seen = 0
    alike = (lambda a, b: (lambda rot, trans: rot[0] < 5.0 and trans[0] < 0.05 * rock1k.diameter)(
        *group.errors(a[None], b)))
    for contacts, _, _ in grasps(rock1k, 4, seed=31):
        arrays = localize(rock1k, contacts, position_noise=tolerance.position_noise, normal_noise_deg=1.0,
                          surface=True, keep="all", diagnose=False).hypotheses.arrays
        reach = stages.PLACEMENT_REACH * fit_threshold(contacts.n)
        leaders = []
        for r in np.flatnonzero((arrays.chi2 <= reach) & ~arrays.fit.underdetermined):
            if not any(alike(arrays.poses[r], arrays.poses[k]) for k in leaders):
                leaders.append(r)
        for started in (arrays.poses[:1], arrays.poses[leaders[:2]]):
            expected = [r for r in leaders if not any(alike(arrays.poses[r], p) for p in started)]
            assert stages._unstarted_placements(rock1k, contacts, arrays, started).tolist() == expected
            seen += len(expected)
    assert seen > 0


def test_the_placements_ends_are_kept_and_the_deadline_stops_them(rock1k):
    """stages._placements_started against brute force: for each leader of the first round
    (every placement but the best's), the least end of its own multistart is among the
    result's rows (a row strictly alike it, χ² no higher); the best χ² never rises; a passed
    deadline returns the hypotheses as they were."""
    tolerance = Tolerance.from_noise(0.0025 * rock1k.diameter, 1.0)
    group = symmetry(rock1k)
    seen = 0
    for contacts, _, _ in grasps(rock1k, 3, seed=41):
        arrays = localize(rock1k, contacts, position_noise=tolerance.position_noise, normal_noise_deg=1.0,
                          surface=True, keep="all", diagnose=False).hypotheses.arrays
        assert stages._placements_started(rock1k, contacts, arrays, tolerance, Deadline(0.0)) is arrays
        out = stages._placements_started(rock1k, contacts, arrays, tolerance, Deadline(None))
        assert out.chi2[0] <= arrays.chi2[0] + 1e-9
        first = stages._unstarted_placements(rock1k, contacts, arrays, arrays.poses[:1])[:stages.PLACEMENT_MULTISTARTS]
        for r in first:
            end = least(multistart_ends(rock1k, contacts, arrays.fit.R[r], arrays.fit.t[r], arrays.facets[r],
                                        tolerance))
            if end[5] >= arrays.chi2[r]:
                continue  # the row stays as it was
            pose = np.eye(4)
            pose[:3, :3], pose[:3, 3] = end[0], end[1]
            rot, trans = group.errors(out.poses, pose)
            near = (rot < 5.0) & (trans < 0.05 * rock1k.diameter)
            assert near.any() and out.chi2[near].min() <= end[5] + 1e-6
            seen += 1
    assert seen > 0
