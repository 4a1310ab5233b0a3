"""The search over surface regions is complete on a fine scanned mesh: with every contact on a
facet and each pair's noise within its tolerance, the tree over the YCB banana's regions holds
the regions of the true facets (a region pair's intervals hold every member pair's:
research/regions.md). The known answer is the true facets; ``localize`` then poses that
placement near the truth. The regions' own extent absorbs most of the noise here (gates 5x too
narrow still join every true tuple; gates of 1 µm and 0.01° lose 4 of 12), so this checks that
nothing is lost on a scan's tessellation, not how tight the intervals are (tests/model/test_table.py
and tests/model/test_object_model.py check those against brute force)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from contactpose import ObjectModel, localize
from contactpose.contacts import Tolerance
from contactpose.geometry.metrics import rotation_error_deg, translation_error
from contactpose.search.grow import grow_tree
from contactpose.sim import grasps as simulate
from contactpose.sim import objects

NOISE = dict(position_noise=0.0005, normal_noise_deg=1.0)


@pytest.fixture(scope="module")
def banana():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ObjectModel.from_mesh(objects.load("ycb:011_banana"))


@pytest.mark.parametrize("n", [3, 4])
def test_the_region_tree_holds_the_true_regions(banana, n):
    assert banana.has_regions and banana.table is None
    tolerance = Tolerance.from_noise(**NOISE)
    labels = banana.patches.labels
    rng = np.random.default_rng(40 + n)
    for _ in range(8):
        g = simulate.grasp(banana, rng, n=n, noise="bounded", **NOISE)
        tree, _ = grow_tree(banana, g.contacts, tolerance)
        assert tree.units == "patches"
        assert (tree.tuples == labels[g.facets]).all(axis=1).any(), f"true regions {labels[g.facets]} not joined"


def test_localize_lists_the_true_placement(banana):
    """Four contacts: some listed hypothesis lies within 5° and 5 % of the diameter of the truth."""
    rng = np.random.default_rng(47)
    for _ in range(4):
        g = simulate.grasp(banana, rng, n=4, noise="bounded", **NOISE)
        poses = localize(banana, g.contacts, diagnose=False, **NOISE).hypotheses.arrays.poses
        near = (rotation_error_deg(poses, g.pose) < 5.0) & (translation_error(poses, g.pose) < 0.05 * banana.diameter)
        assert near.any()
