"""The tree T: joining the admissible pair sets S_ij into n-tuples.

``join_tuples`` (vectorized, most selective pair first) and ``join_tuples_paper``
(node by node in finger order) must both return exactly the tuples of a brute-force
scan over all m**n tuples: ``reference.brute_force_tuples`` and a dense-matrix
scan written here. The set must not depend on the finger order.
"""

import itertools

import numpy as np
import pytest
from conftest import NORMAL_NOISE_DEG, POSITION_NOISE, random_icosahedron
from reference import brute_force_tuples

from contactpose.contacts import Tolerance
from contactpose.model.object_model import ObjectModel
from contactpose.search import pairs as pair_sets
from contactpose.search.pairs import PairSet, admissible_pairs, pair_conditions
from contactpose.search.tree import TripleTest, join_tuples, join_tuples_paper, sorted_rows, triple_tolerance
from contactpose.sim import grasps as simulate

#: (position noise, normal noise °) on the 0.12 m small meshes: tight to very loose, so the
#: joins see from a handful to thousands of tuples.
NOISES = [(0.0005, 1.0), (0.002, 5.0), (0.004, 10.0)]


def as_set(tuples):
    return set(map(tuple, np.asarray(tuples).tolist()))


def dense_brute_force(S, n, m):
    """Independent reference: every m**n tuple tested against a dense m×m matrix per pair."""
    grid = np.stack(np.meshgrid(*[np.arange(m)] * n, indexing="ij"), axis=-1).reshape(-1, n)
    keep = np.ones(len(grid), dtype=bool)
    for (i, j), pairs in S.items():
        M = np.zeros((m, m), dtype=bool)
        M[pairs.first, pairs.second] = True
        keep &= M[grid[:, i], grid[:, j]]
    return grid[keep]


def check_all_joins(S, n, m):
    ref = dense_brute_force(S, n, m)
    fast = join_tuples(S, n)
    paper = join_tuples_paper(S, n)
    brute = brute_force_tuples(S, n, m)
    for got in (fast, paper, brute):
        assert got.shape == (len(ref), n)
        assert np.array_equal(sorted_rows(got), sorted_rows(ref))   # same set, no duplicates
    return ref


@pytest.fixture(scope="module")
def tiny_models():
    """A 20-facet irregular icosahedron and a 12-facet box with uneven sides."""
    import trimesh

    box = trimesh.creation.box(extents=(0.09, 0.05, 0.03))
    box = trimesh.Trimesh(box.vertices, box.faces, process=False)
    return {"ico20": ObjectModel.from_mesh(random_icosahedron(7)),
            "box12": ObjectModel.from_mesh(box)}


@pytest.mark.parametrize("name", ["ico20", "box12"])
@pytest.mark.parametrize("n", [2, 3, 4])
def test_joins_equal_brute_force_on_grasps(tiny_models, name, n):
    model = tiny_models[name]
    rng = np.random.default_rng(100 * n + len(name))
    sizes = []
    for pn, nd in NOISES:
        for _ in range(2):
            g = simulate.grasp(model, rng, n=n, position_noise=pn, normal_noise_deg=nd, noise="bounded")
            tol = Tolerance.from_noise(pn, nd)
            conditions = pair_conditions(g.contacts)
            for bounds, direction in itertools.product(("exact", "paper"), (True, False)):
                S = admissible_pairs(model, conditions, tol, bounds, direction)
                ref = check_all_joins(S, n, model.num_facets)
                sizes.append(len(ref))
                if bounds == "exact":   # the search is complete for noise inside the tolerance
                    assert tuple(g.facets) in as_set(ref)
    assert max(sizes) > 50   # the joins were exercised on large sets too


@pytest.mark.parametrize("n", [2, 3, 4, 5])
@pytest.mark.parametrize("density", [0.05, 0.3, 0.7])
def test_joins_equal_brute_force_on_random_pair_sets(n, density):
    """Arbitrary S_ij, not only geometrically consistent ones."""
    m = 9 if n == 5 else 14
    rng = np.random.default_rng(int(1000 * density) + n)
    S = {}
    for i, j in itertools.combinations(range(n), 2):
        mask = rng.random((m, m)) < density
        first, second = np.nonzero(mask)
        order = rng.permutation(len(first))   # sets need not be sorted
        S[(i, j)] = PairSet(first[order], second[order], m)
    check_all_joins(S, n, m)


def test_joins_with_sorted_key_membership(monkeypatch, tiny_models):
    """Large models use binary search on sorted keys instead of a bitmap: same answer."""
    model = tiny_models["ico20"]
    rng = np.random.default_rng(3)
    g = simulate.grasp(model, rng, n=4, position_noise=0.004, normal_noise_deg=10.0, noise="bounded")
    tol = Tolerance.from_noise(0.004, 10.0)
    ref = check_all_joins(admissible_pairs(model, pair_conditions(g.contacts), tol), 4, model.num_facets)
    monkeypatch.setattr(pair_sets, "BITMAP_MAX_CELLS", 0)
    S = admissible_pairs(model, pair_conditions(g.contacts), tol)
    assert np.array_equal(sorted_rows(join_tuples(S, 4)), sorted_rows(ref))
    assert np.array_equal(sorted_rows(join_tuples_paper(S, 4)), sorted_rows(ref))
    empty = PairSet([], [], model.num_facets)
    assert not empty.contains(np.array([1, 2]), np.array([3, 4])).any()


def test_empty_pair_set_gives_no_tuples():
    m = 6
    full = PairSet(*np.nonzero(np.ones((m, m), dtype=bool)), m)
    S = {(0, 1): full, (0, 2): PairSet([], [], m), (1, 2): full}
    for join in (join_tuples, join_tuples_paper):
        out = join(S, 3)
        assert out.shape == (0, 3) and out.dtype == np.int64


@pytest.mark.parametrize("name", ["ico20", "box12"])
def test_join_is_independent_of_finger_order(tiny_models, name):
    model = tiny_models[name]
    rng = np.random.default_rng(17)
    n = 4
    pn, nd = NOISES[1]
    tol = Tolerance.from_noise(pn, nd)
    g = simulate.grasp(model, rng, n=n, position_noise=pn, normal_noise_deg=nd, noise="bounded")
    ref = as_set(join_tuples(admissible_pairs(model, pair_conditions(g.contacts), tol), n))
    assert len(ref) > 10
    for perm in itertools.permutations(range(n)):
        perm = np.array(perm)
        S = admissible_pairs(model, pair_conditions(g.contacts.permuted(perm)), tol)
        got = join_tuples(S, n)
        back = np.empty_like(got)
        back[:, perm] = got   # new finger i is old finger perm[i]
        assert as_set(back) == ref, perm
        assert len(back) == len(ref)


def test_paper_bounds_and_direction_only_shrink_the_set(rock_model):
    """Vertex-only Δmin >= exact Δmin, and the direction test only removes pairs, so
    S(paper) ⊆ S(exact) and tuples(direction) ⊆ tuples(no direction), with the truth kept."""
    rng = np.random.default_rng(8)
    tol = Tolerance.from_noise(POSITION_NOISE, NORMAL_NOISE_DEG)
    ratios = []
    for _ in range(10):
        g = simulate.grasp(rock_model, rng, n=4, position_noise=POSITION_NOISE,
                           normal_noise_deg=NORMAL_NOISE_DEG, noise="bounded")
        c = pair_conditions(g.contacts)
        sets = {(b, d): as_set(join_tuples(admissible_pairs(rock_model, c, tol, b, d), 4))
                for b in ("exact", "paper") for d in (True, False)}
        assert sets[("paper", True)] <= sets[("exact", True)]
        assert sets[("paper", False)] <= sets[("exact", False)]
        assert sets[("exact", True)] <= sets[("exact", False)]
        assert tuple(g.facets) in sets[("exact", True)]
        ratios.append(len(sets[("exact", False)]) / len(sets[("exact", True)]))
    print(f"\nrock: tuples without / with the direction test, median {np.median(ratios):.2f}x")


def triple_reference(tuples, facet_normals, measured, tol):
    """Rows whose every finger triple a < b < c has |det[n_a, n_b, n_c] - det[m_a, m_b, m_c]| <= tol
    (a scalar, or (m,) per unit: the triple's three values summed)."""
    keep = np.ones(len(tuples), dtype=bool)
    for a, b, c in itertools.combinations(range(tuples.shape[1]), 3):
        got = np.linalg.det(facet_normals[tuples[:, [a, b, c]]])
        want = np.linalg.det(measured[[a, b, c]])
        allowed = tol if np.isscalar(tol) else tol[tuples[:, [a, b, c]]].sum(axis=1)
        keep &= np.abs(got - want) <= allowed
    return tuples[keep]


@pytest.mark.parametrize("name", ["ico20", "box12"])
@pytest.mark.parametrize("n", [3, 4])
def test_join_with_triple_test_equals_filtered_brute_force(tiny_models, name, n):
    """The handedness test inside the tree keeps exactly the brute-force tuples whose triple
    products match, in any finger order."""
    model = tiny_models[name]
    rng = np.random.default_rng(40 + n)
    removed = 0
    for pn, nd in NOISES[1:]:
        g = simulate.grasp(model, rng, n=n, position_noise=pn, normal_noise_deg=nd, noise="bounded")
        tol = Tolerance.from_noise(pn, nd)
        bound = tol.per_contact_bounds()[1]
        S = admissible_pairs(model, pair_conditions(g.contacts), tol)
        triple = TripleTest(model.planes.normals, g.contacts.object_normals, bound)
        want = triple_reference(dense_brute_force(S, n, model.num_facets), model.planes.normals,
                                g.contacts.object_normals, triple_tolerance(bound))
        got = join_tuples(S, n, triple)
        assert np.array_equal(sorted_rows(got), sorted_rows(want))
        assert tuple(g.facets) in as_set(got)
        removed += len(dense_brute_force(S, n, model.num_facets)) - len(want)
        perm = rng.permutation(n)
        c = g.contacts.permuted(perm)
        S_p = admissible_pairs(model, pair_conditions(c), tol)
        got_p = join_tuples(S_p, n, TripleTest(model.planes.normals, c.object_normals, bound))
        back = np.empty_like(got_p)
        back[:, perm] = got_p
        assert as_set(back) == as_set(got)
    if name == "ico20":
        assert removed > 0   # the test does cut mirror-image tuples here (the box has none to cut)


def test_triple_test_with_unit_slack_equals_filtered_brute_force(tiny_models):
    """Units tilted by their own slack (a region's cone): the tree keeps exactly the tuples
    whose triples differ by at most the sum of their units' chords 2 sin((bound + slack)/2),
    and a true tuple whose normals lie within its units' slack survives."""
    model = tiny_models["ico20"]
    rng = np.random.default_rng(9)
    slack = rng.uniform(0.0, np.radians(12.0), model.num_facets)
    pn, nd = NOISES[1]
    removed = 0
    for _ in range(4):
        g = simulate.grasp(model, rng, n=4, position_noise=pn, normal_noise_deg=nd, noise="bounded")
        tol = Tolerance.from_noise(pn, nd)
        bound = tol.per_contact_bounds()[1]
        S = admissible_pairs(model, pair_conditions(g.contacts), tol)
        chords = 2.0 * np.sin((bound + slack) / 2.0)
        want = triple_reference(dense_brute_force(S, 4, model.num_facets), model.planes.normals,
                                g.contacts.object_normals, chords)
        got = join_tuples(S, 4, TripleTest(model.planes.normals, g.contacts.object_normals, bound, slack=slack))
        assert np.array_equal(sorted_rows(got), sorted_rows(want))
        assert tuple(g.facets) in as_set(got)
        removed += len(dense_brute_force(S, 4, model.num_facets)) - len(want)
    assert removed > 0


def test_triple_tolerance_bounds_tilted_determinants():
    """|det[m_a, m_b, m_c] - det[n_a, n_b, n_c]| <= triple_tolerance(θ) whenever each unit m is
    n tilted by at most θ (sampled at the bound, the worst case)."""
    rng = np.random.default_rng(12)
    for theta in (np.radians(0.5), np.radians(2.1), np.radians(10.0)):
        n = rng.normal(size=(20_000, 3, 3))
        n /= np.linalg.norm(n, axis=2, keepdims=True)
        u = np.cross(n, rng.normal(size=n.shape))            # random tangent directions
        u /= np.linalg.norm(u, axis=2, keepdims=True)
        tilted_max = np.cos(theta) * n + np.sin(theta) * u   # tilted by exactly θ
        change = np.abs(np.linalg.det(tilted_max) - np.linalg.det(n))
        assert change.max() <= triple_tolerance(theta)
        assert change.max() > 0.1 * triple_tolerance(theta)   # and the bound is not absurdly loose
