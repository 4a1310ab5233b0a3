"""A baseline probe for next-touch: one candidate drawn at random, scored like the
suggested one (tracking.next_touch.suggest_touch), so that the two compare on one scale."""

from __future__ import annotations

from contactpose.tracking.next_touch import candidate_probes, class_poses, suggest_touch


def random_touch(model, result, *, rng, contacts=None, n_candidates=200, prior="likelihood", standoff=None):
    """A baseline probe: one candidate of :func:`candidate_probes` drawn at random, scored
    like :func:`suggest_touch` would score it."""
    poses, _, _ = class_poses(model, result, prior)
    origins, directions, _ = candidate_probes(model, poses, rng, n_candidates, standoff)
    j = int(rng.integers(len(origins)))
    return suggest_touch(model, result, (origins[j:j + 1], directions[j:j + 1]), rng=rng, contacts=contacts,
                         prior=prior)
