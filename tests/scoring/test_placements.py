"""Placement probabilities against brute force: a box's 24 turns, a symmetric box, and a box
made ambiguous by construction (a corner cut off that no contact touches).

A box of extents 2a × 2b × 2c (a, b, c distinct) maps onto itself under 4 of the 24
axis-aligned turns: the identity and the half turns. Contacts on its faces, away from the
corners, fit the box at the true pose T and at T·G for exactly those 4 turns G, which the
brute force finds by checking every one of the 24 with trimesh's closest points. On the plain
box the 4 are its symmetry group: one placement, and the answer is sure. With one corner cut
off the box has no symmetry left, and the contacts (which avoid the cut and its images) fit
the 4 placements equally: the answer is ambiguous, each placement holds a quarter, and the
truth is listed.
"""

from __future__ import annotations

from itertools import permutations, product

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

import contactpose as cp
from contactpose.model.symmetry import symmetry
from contactpose.scoring.placements import strict_groups

EXTENTS = np.array([0.06, 0.04, 0.025])    # a, b, c: half extents in metres
NOISE = dict(position_noise=2e-5, normal_noise_deg=0.2)
#: Contacts in the object frame: (point on a face, outward normal), away from the corners.
FACE_CONTACTS = [((0.3, 0.2, -1.0), (0, 0, -1)), ((-0.4, -0.1, -1.0), (0, 0, -1)), ((1.0, 0.1, 0.05), (1, 0, 0)),
                 ((0.2, 1.0, -0.1), (0, 1, 0)), ((-0.25, -0.3, 1.0), (0, 0, 1))]


def turns24():
    """The 24 proper rotations that map the axes onto the axes. -> (24, 3, 3)"""
    out = []
    for perm in permutations(range(3)):
        for signs in product((1, -1), repeat=3):
            Q = np.zeros((3, 3))
            Q[np.arange(3), perm] = signs
            if np.linalg.det(Q) > 0:
                out.append(Q)
    return np.array(out)


def box_mesh(cut=False):
    """The box, with the corner (+a, +b, +c) cut off by a plane through the points 30 % of the
    way along its three edges when ``cut``."""
    corners = np.array(list(product((-1, 1), repeat=3))) * EXTENTS
    if cut:
        top = np.flatnonzero((corners > 0).all(axis=1))[0]
        corner = corners[top]
        corners = np.delete(corners, top, axis=0)
        cuts = [corner - 0.6 * EXTENTS[i] * np.eye(3)[i] for i in range(3)]
        corners = np.concatenate([corners, cuts])
    return trimesh.convex.convex_hull(corners)


def grasp(rng):
    """The true pose and the contacts (world frame), with a little noise."""
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    T[:3, 3] = rng.uniform(-0.05, 0.05, 3)
    points = np.array([p for p, _ in FACE_CONTACTS]) * EXTENTS
    normals = np.array([n for _, n in FACE_CONTACTS], dtype=float)
    world = points @ T[:3, :3].T + T[:3, 3] + rng.normal(0.0, NOISE["position_noise"], points.shape)
    return T, cp.Contacts(world, finger_normals=-(normals @ T[:3, :3].T))


def brute_force_fits(mesh, T, contacts, tol=1e-4):
    """(K, 4, 4) the poses T·G over the 24 turns G under which every contact lies on the mesh
    (trimesh's closest point within ``tol``) on a face whose normal is its outward normal."""
    fits = []
    for Q in turns24():
        P = T.copy()
        P[:3, :3] = T[:3, :3] @ Q
        p = (contacts.points - P[:3, 3]) @ P[:3, :3]
        nu = -(contacts.finger_normals @ P[:3, :3])
        _, dist, tri = trimesh.proximity.closest_point(mesh, p)
        if np.all(dist < tol) and np.all(np.einsum("ij,ij->i", mesh.face_normals[tri], nu) > np.cos(np.radians(2))):
            fits.append(P)
    return np.array(fits)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_plain_box_is_one_placement_and_sure(seed):
    mesh = box_mesh()
    model = cp.ObjectModel.from_mesh(mesh)
    T, contacts = grasp(np.random.default_rng(seed))
    fits = brute_force_fits(mesh, T, contacts)
    assert len(fits) == 4  # the identity and the three half turns
    rot, trans = symmetry(model).errors(fits, T)
    assert np.all(rot < 1e-6) and np.all(trans < 1e-9)  # all four are the box's symmetries: one placement
    r = cp.localize(model, contacts, **NOISE)
    assert len(r.placements) == 1 and r.status == "ok" and r.confidence >= 0.99
    assert symmetry(model).errors(r.best.pose, T)[0] < 1.0


@pytest.mark.parametrize("seed", [0, 1])
def test_a_box_with_a_corner_cut_is_ambiguous_among_the_four_turns(seed):
    mesh = box_mesh(cut=True)
    model = cp.ObjectModel.from_mesh(mesh)
    assert len(symmetry(model).rotations) == 1 and not len(symmetry(model).axes)   # no symmetry left
    T, contacts = grasp(np.random.default_rng(seed))
    fits = brute_force_fits(mesh, T, contacts)
    assert len(fits) == 4
    r = cp.localize(model, contacts, **NOISE)
    assert r.status == "ambiguous" and len(r.placements) == 4
    found = np.stack([p.pose for p in r.placements])
    for P in fits:  # each brute-force placement is found, once
        near = [Rotation.from_matrix(P[:3, :3].T @ F[:3, :3]).magnitude() < np.radians(1.0) for F in found]
        assert sum(near) == 1
    probability = np.array([p.probability for p in r.placements])
    assert probability == pytest.approx(np.full(4, 0.25), abs=0.08)
    assert r.confidence == pytest.approx(probability[0], rel=0.02)   # each placement pinned well inside 5°
    assert "4 distinct placements" in r.hint


def test_strict_groups_are_the_brute_force_grouping():
    """Random poses about three centres: each group's members are strictly alike its leader
    (modulo the symmetry), every leader is the best pose not taken before, and no pose is
    left out."""
    rng = np.random.default_rng(5)
    model = cp.ObjectModel.from_mesh(box_mesh())
    sym, D = symmetry(model), model.diameter
    centres = Rotation.random(3, random_state=1).as_matrix()
    poses = np.tile(np.eye(4), (60, 1, 1))
    poses[:, :3, :3] = centres[rng.integers(3, size=60)] @ Rotation.from_rotvec(
        rng.normal(0.0, np.radians(3.0), (60, 3))).as_matrix()
    poses[:, :3, 3] = rng.normal(0.0, 0.02 * D, (60, 3))
    groups = strict_groups(poses, sym, D)
    taken = np.zeros(60, dtype=bool)
    for g in groups:
        lead = g[0]
        assert not taken[lead] and lead == np.flatnonzero(~taken)[0]
        rot, trans = sym.errors(poses, poses[lead])
        alike = (rot < 5.0) & (trans < 0.05 * D) & ~taken
        alike[lead] = True
        assert set(g.tolist()) == set(np.flatnonzero(alike).tolist())
        taken[g] = True
    assert taken.all()


def test_ok_probability_sets_the_bar():
    """The same ambiguous grasp is ok when the bar is below the best placement's confidence,
    and a bad bar is refused in one line."""
    model = cp.ObjectModel.from_mesh(box_mesh(cut=True))
    _, contacts = grasp(np.random.default_rng(0))
    r = cp.localize(model, contacts, **NOISE, ok_probability=0.1)
    assert r.status == "ok" and r.confidence >= 0.1
    with pytest.raises(cp.ContactPoseError, match="ok_probability must be a probability in"):
        cp.localize(model, contacts, **NOISE, ok_probability=1.5)



def test_the_confidence_counts_every_placement_inside_the_best_box():
    """Two placements 5.5° apart along the posterior's loosest turn (the far end of a valley):
    the confidence that the best pose is strictly right is the posterior's mass within 5° and
    5 % of the diameter of it, part of which lies nearer the other placement and is counted by
    that placement's draws. The reference integrates exp(-½ χ²_S) by importance sampling with
    200,000 draws of a Gaussian twice the Laplace width, covering both placements."""
    from types import SimpleNamespace

    from contactpose.contacts import Tolerance
    from contactpose.costs.association import nearest_fit_facets
    from contactpose.geometry.se3 import retract
    from contactpose.scoring.placements import _box_distance, laplace_covariance, placements, surface_chi2

    model = cp.ObjectModel.from_mesh(box_mesh(cut=True))
    group = symmetry(model)
    T, contacts = grasp(np.random.default_rng(4))
    tolerance = Tolerance.from_noise(2e-3, 4.0)                 # a broad posterior: σ of a few degrees
    facets = nearest_fit_facets(model, contacts, T, tolerance)
    covariance = laplace_covariance(model, contacts, T, facets, tolerance)
    sd, loosest = np.sqrt(np.diag(covariance)), np.linalg.eigh(covariance[:3, :3])[1][:, -1]
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec(np.radians(5.5) * loosest).as_matrix()
    poses = np.stack([T, T @ turn])
    arrays = SimpleNamespace(poses=poses, chi2=surface_chi2(model, contacts, poses, facets, tolerance),
                             facets=np.stack([facets, facets]))
    found, confidence = placements(model, contacts, arrays, np.ones(2, dtype=bool), tolerance, group)
    assert len(found) == 2

    xi = np.random.default_rng(0).standard_normal((200_000, 6)) * 2.0 * sd
    R, t = retract(np.repeat(T[None, :3, :3], len(xi), axis=0), np.repeat(T[None, :3, 3], len(xi), axis=0), xi)
    draws = np.zeros((len(xi), 4, 4))
    draws[:, :3, :3], draws[:, :3, 3], draws[:, 3, 3] = R, t, 1.0
    log_w = (-0.5 * surface_chi2(model, contacts, draws, facets, tolerance)
             + 0.5 * np.sum((xi / (2.0 * sd)) ** 2, axis=1))
    w = np.exp(log_w - log_w.max())
    w /= w.sum()
    to_best, to_other = (_box_distance(draws, P, group, model.diameter) for P in poses)
    assert w[(to_best < 1.0) & (to_other < to_best)].sum() > 0.05   # the other's draws hold part of the box
    assert found[0].probability == pytest.approx(w[to_best <= to_other].sum(), abs=0.03)
    assert confidence == pytest.approx(w[to_best < 1.0].sum(), abs=0.05)   # the sampler: sd 0.012 over draw sets


def test_the_evidence_holds_where_the_laplace_width_is_too_narrow():
    """On a rough scan the local curvature of χ²_S is narrower than its valley. Given a
    Laplace covariance three times too narrow (in standard deviation), the sampled evidence
    and strict mass still match a dense reference (200,000 draws of a Gaussian twice the true
    Laplace width): the pilot's own spread shapes the second pass. (Over 15 other draw sets:
    log Z within 0.10 and the strict mass within 0.06, one standard deviation; a single pass
    through the narrow proposal is off by 0.4 and 0.16.)"""
    from contactpose.contacts import Tolerance
    from contactpose.costs.association import nearest_fit_facets
    from contactpose.geometry.se3 import retract
    from contactpose.scoring.placements import _inside_box, laplace_covariance, posterior, surface_chi2

    model = cp.ObjectModel.from_mesh(box_mesh(cut=True))
    T, contacts = grasp(np.random.default_rng(4))
    tolerance = Tolerance.from_noise(2e-3, 4.0)
    facets = nearest_fit_facets(model, contacts, T, tolerance)
    covariance = laplace_covariance(model, contacts, T, facets, tolerance)
    log_z, strict = posterior(model, contacts, T, facets, tolerance, covariance / 9.0, 0.0)

    sd = 2.0 * np.sqrt(np.diag(covariance))
    xi = np.random.default_rng(0).standard_normal((200_000, 6)) * sd
    R, t = retract(np.repeat(T[None, :3, :3], len(xi), axis=0), np.repeat(T[None, :3, 3], len(xi), axis=0), xi)
    draws = np.zeros((len(xi), 4, 4))
    draws[:, :3, :3], draws[:, :3, 3], draws[:, 3, 3] = R, t, 1.0
    log_q = -0.5 * np.sum((xi / sd) ** 2, axis=1) - np.sum(np.log(sd)) - 3.0 * np.log(2.0 * np.pi)
    log_w = -0.5 * surface_chi2(model, contacts, draws, facets, tolerance) - log_q
    w = np.exp(log_w - log_w.max())
    assert log_z == pytest.approx(log_w.max() + np.log(w.mean()), abs=0.3)
    assert strict == pytest.approx(w[_inside_box(xi, model.diameter)].sum() / w.sum(), abs=0.1)
