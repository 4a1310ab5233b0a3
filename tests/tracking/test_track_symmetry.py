"""TrackSet on a symmetric object: the twins of one placement merge into one track, and that
track follows the truth modulo the object's symmetry (model.symmetry), judged against the
symmetry group written out by hand."""

import warnings

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from contactpose import localize
from contactpose.contacts import Tolerance
from contactpose.geometry.metrics import rotation_error_deg, symmetric_errors
from contactpose.model.object_model import ObjectModel
from contactpose.sim import grasps as simulate
from contactpose.tracking.track import MAX_TRACKS, MERGE_DEG, TrackSet

NOISE = dict(position_noise=0.0005, normal_noise_deg=1.0)


@pytest.fixture(scope="module")
def torus():
    """A torus of 24 sections about z (12 around its tube), centred at the origin."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ObjectModel.from_mesh(trimesh.creation.torus(0.05, 0.015, major_sections=24, minor_sections=12))


def _torus_group():
    """The torus's 48 rotations, written out: turns by 15° about z, each also followed by a half
    turn about x. -> (48, 4, 4) (about the origin, its centroid)"""
    turns = [Rotation.from_rotvec([0.0, 0.0, np.radians(15.0 * k)]).as_matrix() for k in range(24)]
    out = np.tile(np.eye(4), (48, 1, 1))
    out[:, :3, :3] = turns + [R @ np.diag([1.0, -1.0, -1.0]) for R in turns]
    return out


def test_twins_of_one_placement_merge_and_track_the_truth(torus):
    """The first grasp's hypotheses hold at least MAX_TRACKS poses that are raw-distinct (more
    than MERGE_DEG apart) yet twins of the true placement; TrackSet keeps one track of them,
    and its error modulo the group (written out by hand) stays below 2° at every touch."""
    rng = np.random.default_rng(0)
    group = _torus_group()
    g = simulate.grasp(torus, rng, n=4, **NOISE)
    result = localize(torus, g.contacts, keep="all", twins=True, **NOISE)
    poses = np.stack([h.pose for h in result.hypotheses])
    twins = poses[symmetric_errors(poses, g.pose, group)[0] < MERGE_DEG]
    raw = rotation_error_deg(twins[:, None], twins[None]) + 1e3 * np.eye(len(twins))
    assert len(twins) >= MAX_TRACKS and raw.min() > MERGE_DEG  # raw merging would keep MAX_TRACKS of them

    tol = Tolerance.from_noise(**NOISE)
    tracks = TrackSet(torus, g.contacts, [(h.facets, h.pose) for h in result.hypotheses], tol)
    errors, counts, X = [symmetric_errors(tracks.best.pose, g.pose, group)[0]], [len(tracks.tracks)], g.pose
    for k in range(6):
        delta = simulate.pose_from(rotvec=0.1 * rng.normal(size=3), translation=0.02 * rng.normal(size=3))
        X = delta @ X
        touch = simulate.grasp(torus, rng, n=1 + k % 2, pose=X, **NOISE)
        best = tracks.add(touch.contacts, hand_motion=(delta, 1.0, 0.001))
        errors.append(symmetric_errors(best, X, group)[0])
        counts.append(len(tracks.tracks))
    assert counts == [1] * 7, counts
    assert max(errors) < 2.0, errors
