"""Touch simulation: the contact a probe measures on the object at its true pose.

A probe (tracking.next_touch.Touch) is cast against the posed object
(tracking.next_touch.predict_outcomes); the contact it meets gets bounded Gaussian sensor
noise, as ``simulate.grasp(noise="bounded")`` gives a grasp's contacts.
"""

from __future__ import annotations

import numpy as np

from contactpose.contacts import Contacts, Tolerance
from contactpose.errors import ContactPoseError
from contactpose.geometry.sampling import perturb_normals
from contactpose.tracking.next_touch import CONTACT, predict_outcomes


def simulate_touch(model, pose, touch, rng=None, *, position_noise=0.0, normal_noise_deg=0.0):
    """The contact a probe measures on the object at the true ``pose``.

    Returns (point (3,), outward object normal (3,)) in the world frame, with bounded
    Gaussian noise as in ``simulate.grasp(noise="bounded")``, or None when the probe
    misses (or starts inside the object).
    """
    kind, points, normals, _ = predict_outcomes(model, pose[None], touch.start[None], touch.direction[None])
    if kind[0, 0] != CONTACT:
        return None
    point, normal = points[0, 0], normals[0, 0]
    if position_noise > 0 and normal_noise_deg > 0:
        if rng is None:
            raise ContactPoseError("simulate_touch needs rng when noise is given")
        pos_bound, ang_bound = Tolerance.from_noise(position_noise, normal_noise_deg).per_contact_bounds()
        err = rng.normal(0.0, position_noise, 3)
        while np.linalg.norm(err) > pos_bound:
            err = rng.normal(0.0, position_noise, 3)
        point = point + err
        normal = perturb_normals(normal[None], np.radians(normal_noise_deg), rng, ang_bound)[0]
    return point, normal


def with_contact(contacts, point, object_normal):
    """The contacts plus one more (world point, outward object normal)."""
    return Contacts(np.vstack([contacts.points, point]),
                    object_normals=np.vstack([contacts.object_normals, object_normal]))
