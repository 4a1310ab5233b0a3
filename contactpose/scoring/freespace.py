"""Free-space check: a finger sits outside the object.

A hypothesis puts contact i on facet k under the pose T = (R, t). In the object frame
the contact is p_i = Rᵀ(x̃_i - t) and the finger comes from the direction
u_i = -Rᵀñ_i, away from the object. If a ray from the surface along u_i enters the
object again within the finger radius r, the contact lies in a concavity too narrow
for the finger, and the hypothesis is rejected.

* The ray starts on facet k's plane (the foot of p_i), ``START_REL`` · diameter off it.
* Only *entering* hits count (the ray meets a facet from its outer side, u·n < 0).
  A ray that starts just inside the surface, through noise, first leaves the object:
  that exit is not a violation, so the test never depends on the sign of the noise.
* ``fingertip="ball"`` also checks the fingertip sphere of radius r resting on the
  contact: its centre p_i + r·u_i must be at least r - ``slack`` from the surface.
  This catches a finger at the bottom of a narrow slot, where the ray runs out of the
  slot freely. A true contact of a spherical fingertip of radius >= r passes both
  tests when the noise (``slack``) is accounted for: the ray segment of length r lies
  inside the fingertip's ball as long as the normal error is below 60°.

Rays are cast by the model's :func:`~contactpose.geometry.raycast.raycaster`.
"""

from __future__ import annotations

import logging

import numpy as np

from contactpose.costs.facet import offset_residuals
from contactpose.costs.frame import object_frame
from contactpose.errors import ContactPoseError
from contactpose.geometry.raycast import raycaster

log = logging.getLogger(__name__)

#: Rays start this fraction of the object diameter off the facet plane.
START_REL = 1e-6
FINGERTIPS = ("ray", "ball")
#: Default clearance allowance of the "ball" test, as a fraction of the finger radius:
#: a true fingertip's centre sits r·cos θ from its facet for a normal error θ, and
#: 0.1 r covers θ up to 25° plus position error up to a tenth of the radius.
BALL_SLACK_REL = 0.1

def free_space_violations(model, facets, poses, contacts, finger_radius, *, per_contact=False,
                          fingertip="ray", slack=None):
    """Which hypotheses put a contact where no finger fits.

    model : ObjectModel; facets : (H, n) int, the facet of each contact (-1: unassigned
    finger, never a violation); poses : (H, 4, 4) T_world_object; contacts : Contacts
    (world frame); finger_radius : r > 0, length units; fingertip : "ray" (the outward
    normal ray of length r re-enters the object) or "ball" (also: the fingertip sphere of
    radius r on the contact comes closer than r - slack to the surface); slack : length,
    the noise allowance of the "ball" test (default BALL_SLACK_REL · r).
    Returns (H,) bool, True where some contact is violated, or (H, n) bool with
    ``per_contact=True``.
    """
    facets = np.asarray(facets)
    poses = np.asarray(poses, dtype=np.float64)
    if facets.ndim != 2 or facets.shape[1] != contacts.n:
        raise ContactPoseError(f"facets must have shape (H, {contacts.n}), got {facets.shape}")
    if poses.shape != (len(facets), 4, 4):
        raise ContactPoseError(f"poses must have shape ({len(facets)}, 4, 4), got {poses.shape}")
    if not (np.isfinite(finger_radius) and finger_radius > 0):
        raise ContactPoseError(f"finger_radius must be a positive length, got {finger_radius!r}")
    if fingertip not in FINGERTIPS:
        raise ContactPoseError(f"fingertip must be one of {FINGERTIPS}, got {fingertip!r}")
    h, n = facets.shape
    if h == 0:
        return np.zeros((0, n) if per_contact else 0, dtype=bool)
    assigned = facets >= 0
    k = np.where(assigned, facets, 0)
    # contacts and outward finger directions in each hypothesis' object frame: (H, n, 3)
    p, u = object_frame(poses[:, :3, :3], poses[:, :3, 3], contacts.points, contacts.finger_normals)
    # foot of each contact on its facet's plane, then a hair outward
    n_k = model.planes.normals[k]
    foot = p - offset_residuals(p, n_k, model.planes.offsets[k])[..., None] * n_k
    origins = foot + START_REL * model.diameter * u
    caster = raycaster(model)
    bad = caster.entering_within(origins.reshape(-1, 3), u.reshape(-1, 3), finger_radius).reshape(h, n)
    if fingertip == "ball":
        slack = BALL_SLACK_REL * finger_radius if slack is None else float(slack)
        # fingertip sphere resting on the contact: centre r along u, clearance r - slack
        centres = foot + finger_radius * u
        bad |= caster.distance(centres.reshape(-1, 3)).reshape(h, n) < finger_radius - slack
    bad &= assigned
    return bad if per_contact else bad.any(axis=1)


def drop_blocked(model, contacts, arrays, finger_radius):
    """The hypotheses but those whose (determined) pose puts a contact where no finger of
    ``finger_radius`` fits (:func:`free_space_violations`)."""
    bad = free_space_violations(model, arrays.facets, arrays.poses, contacts, finger_radius)
    return arrays.take(np.flatnonzero(~(bad & ~arrays.fit.underdetermined)))
