"""Free-space check (contactpose.scoring.freespace) on a hand-made U-channel, against analytic
geometry and a brute-force per-ray Möller–Trumbore loop."""

import numpy as np
import pytest
import trimesh
from conftest import NORMAL_NOISE_DEG, POSITION_NOISE

from contactpose.contacts import Contacts
from contactpose.errors import ContactPoseError
from contactpose.geometry.raycast import raycaster
from contactpose.model.object_model import ObjectModel
from contactpose.scoring.freespace import START_REL, free_space_violations
from contactpose.sim import grasps as simulate

# U-channel profile in x-y, extruded along z: outer 60 x 40 mm, a slot 8 mm wide
# (x in [A, B]) from the floor y = FLOOR up to the open top y = HEIGHT, 50 mm long.
WIDTH, HEIGHT, FLOOR, SLOT, LENGTH = 0.06, 0.04, 0.01, 0.008, 0.05
A, B = (WIDTH - SLOT) / 2, (WIDTH + SLOT) / 2


def u_channel():
    v2 = np.array([(0, 0), (WIDTH, 0), (WIDTH, FLOOR), (B, FLOOR), (A, FLOOR), (0, FLOOR),
                   (0, HEIGHT), (A, HEIGHT), (B, HEIGHT), (WIDTH, HEIGHT)], float)
    f2 = np.array([(0, 1, 2), (0, 2, 3), (0, 3, 4), (0, 4, 5), (5, 4, 7), (5, 7, 6), (3, 2, 9), (3, 9, 8)])
    mesh = trimesh.creation.extrude_triangulation(v2, f2, LENGTH)
    assert mesh.is_watertight and mesh.volume > 0
    return mesh


@pytest.fixture(scope="module")
def channel():
    return ObjectModel.from_mesh(u_channel())


def facet_at(model, point, normal):
    """The facet containing an object-frame point with the given outward normal."""
    on_plane = np.abs(model.planes.normals @ point + model.planes.offsets) < 1e-9
    aligned = model.planes.normals @ normal > 0.999
    cand = np.flatnonzero(on_plane & aligned)
    tri = model.triangles[cand]
    # barycentric inside test
    for k, t in zip(cand, tri):
        v0, v1, v2 = t[1] - t[0], t[2] - t[0], point - t[0]
        d00, d01, d11, d20, d21 = v0 @ v0, v0 @ v1, v1 @ v1, v2 @ v0, v2 @ v1
        den = d00 * d11 - d01 * d01
        v, w = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
        if v >= -1e-12 and w >= -1e-12 and v + w <= 1 + 1e-12:
            return int(k)
    raise AssertionError(f"no facet at {point}")


# object-frame probe sites: (name, point, outward normal)
SITES = [
    ("left wall", (A, 0.025, 0.025), (1.0, 0, 0)),
    ("right wall", (B, 0.03, 0.02), (-1.0, 0, 0)),
    ("floor", (WIDTH / 2, FLOOR, 0.025), (0, 1.0, 0)),
    ("outer side", (0.0, 0.02, 0.025), (-1.0, 0, 0)),
    ("bottom", (0.02, 0.0, 0.03), (0, -1.0, 0)),
    ("wall top", (0.01, HEIGHT, 0.02), (0, 1.0, 0)),
]


def site_contacts(model, pose):
    """Contacts at the SITES under ``pose`` (exact) and their facets."""
    pts = np.array([s[1] for s in SITES])
    nrm = np.array([s[2] for s in SITES])
    facets = np.array([facet_at(model, p, n) for p, n in zip(pts, nrm)])
    R, t = pose[:3, :3], pose[:3, 3]
    return Contacts(pts @ R.T + t, object_normals=nrm @ R.T), facets


@pytest.mark.parametrize("radius, expect", [
    (2 * SLOT, [True, True, False, False, False, False]),     # the finger spans more than the slot
    (0.5 * SLOT, [False, False, False, False, False, False]),  # a thin finger fits between the walls
])
def test_ray_check_matches_analytic_slot(channel, radius, expect):
    pose = simulate.random_pose(np.random.default_rng(3), max_translation=0.05)
    contacts, facets = site_contacts(channel, pose)
    bad = free_space_violations(channel, facets[None], pose[None], contacts, radius, per_contact=True)
    assert bad.shape == (1, len(SITES))
    assert bad[0].tolist() == expect
    assert free_space_violations(channel, facets[None], pose[None], contacts, radius).tolist() == [any(expect)]


def test_ball_check_catches_the_slot_floor(channel):
    """A ray from the floor runs out of the open slot; the fingertip sphere does not fit."""
    pose = simulate.random_pose(np.random.default_rng(4), max_translation=0.05)
    contacts, facets = site_contacts(channel, pose)
    wide = free_space_violations(channel, facets[None], pose[None], contacts, 2 * SLOT, per_contact=True,
                                 fingertip="ball")[0]
    assert wide.tolist() == [True, True, True, False, False, False]
    # radius below half the slot (less the slack): the ball sits on the floor between the walls
    thin = free_space_violations(channel, facets[None], pose[None], contacts, 0.4 * SLOT, per_contact=True,
                                 fingertip="ball")[0]
    assert not thin.any()


def moller_trumbore_entering(origin, direction, triangles, normals, length):
    """Reference twin: does the ray enter any triangle (outer side) at 0 < t <= length?
    One ray against every triangle (Möller–Trumbore, float64)."""
    e1, e2 = triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    pvec = np.cross(direction, e2)
    det = np.einsum("ki,ki->k", e1, pvec)
    ok = np.abs(det) > 1e-15
    det = np.where(ok, det, 1.0)
    tvec = origin - triangles[:, 0]
    u = np.einsum("ki,ki->k", tvec, pvec) / det
    qvec = np.cross(tvec, e1)
    v = qvec @ direction / det
    t = np.einsum("ki,ki->k", e2, qvec) / det
    inside = ok & (u >= 0) & (v >= 0) & (u + v <= 1)
    return bool(np.any(inside & (t > 0) & (t <= length) & (normals @ direction < 0)))


def reference_violations(model, facets, poses, contacts, radius):
    """free_space_violations(per_contact=True) by a plain loop over hypotheses, contacts, triangles."""
    out = np.zeros(facets.shape, dtype=bool)
    for h in range(len(facets)):
        R, t = poses[h, :3, :3], poses[h, :3, 3]
        for i, k in enumerate(facets[h]):
            if k < 0:
                continue
            p = R.T @ (contacts.points[i] - t)
            u = -R.T @ contacts.finger_normals[i]
            n_k = model.planes.normals[k]
            foot = p - (n_k @ p + model.planes.offsets[k]) * n_k
            origin = foot + START_REL * model.diameter * u
            out[h, i] = moller_trumbore_entering(origin, u, model.triangles, model.planes.normals, radius)
    return out


def test_matches_brute_force_rays(channel):
    """Random grasps of the channel, each scored under its true facets and under random
    wrong facets and poses: the batched check equals the per-ray loop."""
    rng = np.random.default_rng(11)
    for _ in range(6):
        g = simulate.grasp(channel, rng, n=5, position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG,
                           noise="bounded", max_translation=0.03)
        h = 12
        facets = rng.integers(0, channel.num_facets, (h, g.contacts.n))
        facets[0] = g.facets
        facets[1, 2] = -1  # an unassigned finger
        poses = np.stack([g.pose] + [simulate.random_pose(rng, max_translation=0.03) @ g.pose
                                     if j % 2 else g.pose for j in range(1, h)])
        for radius in (0.5 * SLOT, 2 * SLOT, 0.03):
            got = free_space_violations(channel, facets, poses, g.contacts, radius, per_contact=True)
            want = reference_violations(channel, facets, poses, g.contacts, radius)
            assert got.tolist() == want.tolist()
            assert not got[1, 2]


def test_true_contacts_pass_on_convex_and_irregular_objects(rock_model, box_model):
    """Completeness: true hypotheses under bounded noise are never rejected on objects
    without narrow concavities, at a 1 cm finger."""
    rng = np.random.default_rng(5)
    for model in (rock_model, box_model):
        for _ in range(100):
            g = simulate.grasp(model, rng, n=4, position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG,
                               noise="bounded")
            bad = free_space_violations(model, g.facets[None], g.pose[None], g.contacts, 0.01, fingertip="ball",
                                        slack=0.001)
            assert not bad[0]


def test_caster_is_cached_per_model(channel, rock_model):
    assert raycaster(channel) is raycaster(channel)
    assert raycaster(channel) is not raycaster(rock_model)


def test_first_hits_agree_with_trimesh(rock_model):
    rng = np.random.default_rng(2)
    mesh = trimesh.Trimesh(rock_model.vertices, rock_model.faces, process=False)
    dirs = rng.normal(size=(200, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = -0.2 * dirs + rng.normal(0, 0.01, (200, 3))
    t, facet = raycaster(rock_model).first_hits(origins, dirs)
    tri, ray = trimesh.ray.ray_triangle.RayMeshIntersector(mesh).intersects_id(origins, dirs, multiple_hits=False)
    want = -np.ones(200, dtype=int)
    want[ray] = tri
    assert np.mean(facet == want) > 0.99  # float32 vs float64 may split a ray on an edge
    assert np.all(np.isfinite(t) == (facet >= 0))


def test_bad_input(channel):
    pose = np.eye(4)[None]
    contacts, facets = site_contacts(channel, np.eye(4))
    with pytest.raises(ContactPoseError, match="facets must have shape"):
        free_space_violations(channel, facets[None, :3], pose, contacts, 0.01)
    with pytest.raises(ContactPoseError, match="poses must have shape"):
        free_space_violations(channel, facets[None], np.eye(4), contacts, 0.01)
    with pytest.raises(ContactPoseError, match="finger_radius"):
        free_space_violations(channel, facets[None], pose, contacts, 0.0)
    with pytest.raises(ContactPoseError, match="fingertip"):
        free_space_violations(channel, facets[None], pose, contacts, 0.01, fingertip="cone")
    empty = free_space_violations(channel, np.zeros((0, 6), int), np.zeros((0, 4, 4)), contacts, 0.01)
    assert empty.shape == (0,)


def test_localize_drops_hypotheses_no_finger_can_make(channel):
    """localize(..., finger_radius=r) keeps exactly the hypotheses that are underdetermined or
    pass the ray check, and the true tuple among them, on grasps a wide finger can make."""
    from contactpose.localize import localize

    rng = np.random.default_rng(12)
    noise = dict(position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG)
    dropped = 0
    for _ in range(25):
        g = simulate.grasp(channel, rng, n=4, noise="bounded", **noise)
        if free_space_violations(channel, g.facets[None], g.pose[None], g.contacts, 2 * SLOT)[0]:
            continue  # a true contact no wide finger could make
        full = localize(channel, g.contacts, twins=True, **noise).hypotheses.arrays
        kept = localize(channel, g.contacts, finger_radius=2 * SLOT, twins=True, **noise).hypotheses.arrays
        bad = free_space_violations(channel, full.facets, full.poses, g.contacts, 2 * SLOT) & ~full.fit.underdetermined
        assert sorted(map(tuple, kept.facets)) == sorted(map(tuple, full.facets[~bad]))
        labels = channel.patches.labels if channel.patch_table is not None else np.arange(channel.num_facets)
        assert (labels[kept.facets] == labels[g.facets]).all(axis=1).any()
        dropped += bad.sum()
    assert dropped > 0
