"""`make demo`: the paper's §5 banana protocol on the built-in banana, fast and paper methods."""

from __future__ import annotations

import os

import numpy as np

from contactpose.geometry.metrics import rotation_error_deg, translation_error
from contactpose.harness.viz import plot_localization
from contactpose.localize import localize, warm_up
from contactpose.model.object_model import ObjectModel
from contactpose.options import fit_threshold
from contactpose.sim import grasps as simulate
from contactpose.sim import objects

#: Tolerance settings of the demo (the paper gives none): 0.5 mm and 1° sensor noise.
DEMO_POSITION_NOISE = 0.0005
DEMO_NORMAL_NOISE_DEG = 1.0


def run_demo(seed=0, out_dir="results/demo"):
    """Build the banana model, grasp it with 4 fingers at facet centroids, localize, draw.
    Times after a warm-up: a first build (the one timed is the second), and localize on
    another grasp of the same model (localize.warm_up: the first calls on a model load
    kernels and find its symmetry)."""
    rng = np.random.default_rng(seed)
    mesh = objects.load("banana")
    ObjectModel.from_mesh(mesh)  # loads the build's kernels
    model = ObjectModel.from_mesh(mesh)
    warm = simulate.grasp(model, rng, n=4, pose=simulate.paper_pose(), where="centroid")
    g = simulate.grasp(model, rng, n=4, pose=simulate.paper_pose(), where="centroid")
    print(f"banana: {model.num_facets} facets, {model.num_pairs} ordered pairs, "
          f"built in {model.build_seconds['total'] * 1000:.1f} ms (timings after a warm-up run)")
    print(f"true facets: {g.facets.tolist()} (roll 5.7°, shift 10 mm in x, y, z)")
    warm_up(model, warm.contacts, position_noise=DEMO_POSITION_NOISE, normal_noise_deg=DEMO_NORMAL_NOISE_DEG)
    results = {}
    for method in ("fast", "paper"):
        r = localize(model, g.contacts, position_noise=DEMO_POSITION_NOISE,
                     normal_noise_deg=DEMO_NORMAL_NOISE_DEG, method=method)
        results[method] = r
        b = r.best
        err = (f"rotation error {rotation_error_deg(b.pose, g.pose):.3f}°, "
               f"translation error {translation_error(b.pose, g.pose) * 1000:.3f} mm") if b else "no pose"
        print(f"[{method:5s}] status {r.status}, {r.num_hypotheses} hypotheses, best facets "
              f"{b.facets.tolist() if b else None}, {err}, online {r.timing['total'] * 1000:.2f} ms")
    os.makedirs(out_dir, exist_ok=True)
    path = os.path.join(out_dir, "banana_demo.png")
    best = results["fast"].best
    if best is not None:
        costs = {m: r.hypotheses.arrays.chi2 for m, r in results.items()}
        plot_localization(model, g.contacts, best.pose, path, true_pose=g.pose, costs=costs,
                          threshold=fit_threshold(g.contacts.n),
                          title=f"banana, 4 contacts: best facets {best.facets.tolist()}")
        print(f"picture: {path}")
    return 0
