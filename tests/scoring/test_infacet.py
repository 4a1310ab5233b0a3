"""The in-facet check (contactpose.scoring.infacet): a lower bound on the best full χ² of a hypothesis.

References: scipy's least squares on the whitened residuals (normal, offset and lateral,
residuals.py) started from the closed form, which finds a pose the bound must not beat;
and the true facet tuple of grasps whose noise lies inside the tolerance, which must pass.
"""

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from contactpose.costs import facet
from contactpose.localize import localize
from contactpose.options import fit_threshold
from contactpose.scoring.infacet import within_noise
from contactpose.scoring.rank import closed_form_arrays
from contactpose.sim import grasps as simulate
from contactpose.solvers.polish import lowest_chi2_bound

POSITION_NOISE, NORMAL_NOISE_DEG = 0.0005, 1.0


def full_chi2(model, contacts, facets, T, tolerance):
    r_n, r_o, r_l = facet.contact_residuals(T[None, :3, :3], T[None, :3, 3], model.planes.normals[facets][None],
                                          model.planes.offsets[facets][None], model.triangles[facets][None],
                                          contacts.points, contacts.finger_normals)
    return float(facet.whitened_cost(r_n, r_o, r_l, tolerance.normal_noise, tolerance.position_noise)[0])


def refined_chi2(model, contacts, facets, T0, tolerance):
    """Least squares on the full χ² from T0, in the right perturbation of the pose."""
    def residual(xi):
        T = T0.copy()
        T[:3, :3] = T0[:3, :3] @ Rotation.from_rotvec(xi[:3]).as_matrix()
        T[:3, 3] = T0[:3, 3] + T0[:3, :3] @ xi[3:]
        r_n, r_o, r_l = facet.contact_residuals(T[None, :3, :3], T[None, :3, 3], model.planes.normals[facets][None],
                                              model.planes.offsets[facets][None], model.triangles[facets][None],
                                              contacts.points, contacts.finger_normals)
        return np.concatenate([r_n.ravel() / tolerance.normal_noise,
                               np.concatenate([r_o, r_l], axis=1).ravel() / tolerance.position_noise])

    return float(np.sum(least_squares(residual, np.zeros(6), method="trf", xtol=1e-12, ftol=1e-12).fun ** 2))


def located(model, seed, count):
    """(grasp, localize result) of ``count`` random 4-finger grasps, noise inside the tolerance."""
    rng = np.random.default_rng(seed)
    for _ in range(count):
        g = simulate.grasp(model, rng, n=4, position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG,
                           noise="bounded")
        yield g, localize(model, g.contacts, position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG,
                          distinct=False)


@pytest.mark.parametrize("name", ["rock_model", "banana_model"])
def test_bound_never_exceeds_the_refined_chi2(name, request):
    """For every checked hypothesis near the fit threshold, the bound lies below the χ² that
    least squares reaches from the closed form (up to the first-order error of the bound,
    which grows with the distance the pose must move: far from fitting, it does not matter)."""
    model = request.getfixturevalue(name)
    checked = 0
    for g, r in located(model, 21, 12):
        a = r.hypotheses.arrays
        rows = np.flatnonzero(~a.fit.underdetermined)[:20]
        if len(rows) == 0:
            continue
        bound = lowest_chi2_bound(model, g.contacts, a, rows, r.tolerance)
        for row, b in zip(rows, bound):
            refined = refined_chi2(model, g.contacts, a.facets[row], a.poses[row], r.tolerance)
            assert refined <= a.chi2[row] + 1e-9
            if refined <= 3 * fit_threshold(4):
                assert b <= refined * (1 + 1e-3) + 1e-6, (row, b, refined)
                checked += 1
    assert checked > 20


@pytest.mark.parametrize("name", ["rock_model", "banana_model", "carton_model"])
def test_true_tuple_passes_within_tolerance(name, request):
    """Completeness: noise inside the tolerance never makes the true hypothesis fail, while the
    χ² at the pose localize found (polished or not) does fail some of them on the banana."""
    model = request.getfixturevalue(name)
    labels = model.patches.labels if model.patch_table is not None else np.arange(model.num_facets)
    old_fails = 0
    for g, r in located(model, 22, 80):
        a = r.hypotheses.arrays
        true = np.flatnonzero((labels[a.facets] == labels[g.facets]).all(axis=1))
        assert len(true)
        ok = within_noise(model, g.contacts, a, r.tolerance, fit_threshold(4))
        assert ok[true].any()
        old_fails += a.chi2[true].min() > fit_threshold(4)
    if name == "banana_model":
        assert old_fails > 0   # the grasps exercise the bound, not only the plain χ² test


def test_gaussian_grasp_whose_closed_form_misfits_still_passes(banana_model):
    """A true tuple the plane-χ² pre-test used to reject: Gaussian noise, χ² 230 at the closed
    form, but the true pose itself fits (χ² below the threshold), so some pose within noise
    exists and the tuple must pass."""
    sx = 0.0025 * banana_model.diameter
    g = simulate.grasp(banana_model, np.random.default_rng(331), n=4, position_noise=sx, normal_noise_deg=1.0)
    r = localize(banana_model, g.contacts, position_noise=sx, normal_noise_deg=1.0)
    a = closed_form_arrays(banana_model, g.contacts, np.asarray(g.facets)[None], r.tolerance)
    assert full_chi2(banana_model, g.contacts, g.facets, g.pose, r.tolerance) <= fit_threshold(4) < a.chi2[0]
    assert within_noise(banana_model, g.contacts, a, r.tolerance, fit_threshold(4))[0]


def test_bound_rejects_what_no_pose_can_fit(rock_model):
    """A hypothesis whose contact lies far outside its triangle fails, and the bound agrees
    with the least-squares optimum then."""
    model = rock_model
    g, r = next(located(model, 23, 1))
    a = r.hypotheses.arrays
    ok = within_noise(model, g.contacts, a, r.tolerance, fit_threshold(4))
    rejected = np.flatnonzero(~ok & ~a.fit.underdetermined)
    assert len(rejected)
    for row in rejected[:5]:
        assert refined_chi2(model, g.contacts, a.facets[row], a.poses[row], r.tolerance) > fit_threshold(4)


def test_enough_stops_early_without_changing_the_first_fits(rock_model):
    """within_noise(..., enough=K) marks the same first K fitting hypotheses (in rank order)
    as the full check."""
    model = rock_model
    compared = 0
    for g, r in located(model, 24, 10):
        a = r.hypotheses.arrays
        full = np.flatnonzero(within_noise(model, g.contacts, a, r.tolerance, fit_threshold(4)))
        for k in (1, 3, 10):
            part = np.flatnonzero(within_noise(model, g.contacts, a, r.tolerance, fit_threshold(4), enough=k))
            assert part[:k].tolist() == full[:k].tolist()
            compared += len(full) > k
    assert compared > 3


def test_patch_members_off_the_chosen_plane_still_pass(carton_model):
    """On a model with patches the closed form fits the member facets the search picked;
    another member, up to the patch tolerance off that plane, can fit the contact better, so
    a plane χ² above the threshold is no reason to reject. Grasps 86 and 274 of this stream
    were lost that way."""
    model = carton_model
    labels = model.patches.labels
    for g, r in located(model, 5, 300):
        a = r.hypotheses.arrays
        true = np.flatnonzero((labels[a.facets] == labels[g.facets]).all(axis=1))
        assert within_noise(model, g.contacts, a, r.tolerance, fit_threshold(4))[true].any()


def test_polished_poses_lower_the_full_chi2(rock_model, banana_model):
    """localize moves the poses of hypotheses that could beat the best toward the least full
    χ²: every returned χ² is the exact χ² at the returned pose, never above the closed form's
    for the same facets, and in some grasps well below it; least squares from the polished
    best pose finds little more."""
    from contactpose.solvers.closed_form import fit_poses

    improved, gaps = 0, []
    for model in (rock_model, banana_model):
        for g, r in located(model, 25, 25):
            b = r.best
            assert full_chi2(model, g.contacts, b.facets, b.pose, r.tolerance) == pytest.approx(b.chi2, rel=1e-9)
            fit = fit_poses(model.planes.normals[b.facets][None], model.planes.offsets[b.facets][None],
                            g.contacts.points, g.contacts.finger_normals, angle_tol=r.tolerance.normal_noise,
                            centroids=model.centroids[b.facets][None])
            closed = full_chi2(model, g.contacts, b.facets, fit.poses()[0], r.tolerance)
            assert b.chi2 <= closed + 1e-9
            improved += b.chi2 < closed - 0.5
            gaps.append(b.chi2 - refined_chi2(model, g.contacts, b.facets, b.pose, r.tolerance))
    assert improved >= 5
    assert np.median(gaps) < 0.1


def test_member_runs_do_not_change_the_bound(monkeypatch):
    """On a box whose faces are regions of 128 facets, the bound (and the pose its
    minimisation reaches) with the members in runs of GROUP_FACETS equals the bound with
    every member its own run: a run's sphere only skips members that cannot be closest."""
    import trimesh

    from contactpose.model.object_model import ObjectModel
    from contactpose.model.patches import MemberGroups

    mesh = trimesh.creation.box(extents=(0.10, 0.06, 0.04))
    for _ in range(3):
        mesh = mesh.subdivide()
    model = ObjectModel.from_mesh(trimesh.Trimesh(mesh.vertices, mesh.faces, process=False))
    checked = 0
    for g, r in located(model, 3, 12):
        a = r.hypotheses.arrays
        rows = np.arange(min(len(a.cost), 64))
        runs = lowest_chi2_bound(model, g.contacts, a, rows, r.tolerance)
        monkeypatch.setitem(model.__dict__, "member_groups",
                            MemberGroups.of(model.triangles, model.facet_radii, model.patches, run=1))
        single = lowest_chi2_bound(model, g.contacts, a, rows, r.tolerance)
        monkeypatch.undo()
        assert np.allclose(runs, single, rtol=1e-12, atol=1e-12)
        checked += len(rows)
    assert checked > 50
