"""Tests of contactpose.geometry.kernels against independent references.

References: trimesh's closest point, dense sampling (segments and barycentric
grids on facets, nearest pairs by cKDTree), numpy brute force, and distances
known in closed form for hand-built configurations.
"""


import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from contactpose.errors import ContactPoseError
from contactpose.geometry import kernels as g

#: Grid subdivisions per facet edge for the sampling reference.
GRID = 40
#: Samples per segment for the sampling reference.
SEG_SAMPLES = 2001
#: Rounding slack of the kernels on unit-sized inputs.
ROUND = 1e-9


# ----------------------------------------------------------------- helpers ---

def _bary_grid(n):
    """(K, 3) barycentric weights of the grid with n subdivisions per edge."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = i + j <= n
    i, j = i[keep], j[keep]
    return np.column_stack([n - i - j, i, j]) / n


WEIGHTS = _bary_grid(GRID)


def _sample_tri(tri):
    return WEIGHTS @ tri


def _sample_seg(p, q):
    s = np.linspace(0.0, 1.0, SEG_SAMPLES)[:, None]
    return p + s * (q - p)


def _max_edge(tri):
    return max(np.linalg.norm(tri[i] - tri[(i + 1) % 3]) for i in range(3))


def _grid_resolution(tri):
    # Each grid cell is a copy of the facet scaled by 1/GRID, so its diameter
    # (= its longest edge) is max_edge / GRID and every point of the facet is
    # within that distance of a grid node. Factor 1 per facet suffices.
    return _max_edge(tri) / GRID


def _sampled_tri_tri(a, b):
    d, _ = cKDTree(_sample_tri(b)).query(_sample_tri(a), k=1)
    return d.min()


def _exact(a, b):
    return np.sqrt(g.triangle_triangle_dist2(a[0], a[1], a[2], b[0], b[1], b[2]))


def _check_against_sampling(a, b):
    """Exact distance vs dense sampling; returns the exact distance."""
    exact = _exact(a, b)
    sampled = _sampled_tri_tri(a, b)
    # Closest points x* on a, y* on b each have a grid node within the
    # resolution of their facet: sampled <= exact + res(a) + res(b).
    assert sampled >= exact - ROUND
    assert sampled - exact <= _grid_resolution(a) + _grid_resolution(b)
    return exact


def _random_triangles(rng, n, scale=1.0):
    return rng.standard_normal((n, 3, 3)) * scale


# ------------------------------------------------------- point - triangle ---

def test_point_triangle_matches_trimesh():
    rng = np.random.default_rng(1)
    tris = _random_triangles(rng, 2000)
    pts = rng.standard_normal((2000, 3)) * 2.0
    ref = trimesh.triangles.closest_point(tris, pts)
    x = g.closest_points_on_triangles(pts, tris)
    d = g.point_triangle_distance(pts, tris)
    np.testing.assert_allclose(x, ref, atol=1e-9)
    np.testing.assert_allclose(d, np.linalg.norm(pts - ref, axis=1), atol=1e-9)
    for i in range(20):
        assert np.isclose(g.point_triangle_dist2(pts[i], *tris[i]), d[i] ** 2, atol=1e-9)
        np.testing.assert_allclose(g.closest_point_triangle(pts[i], *tris[i]), x[i])


DEGENERATE = {
    "collinear": [[0, 0, 0], [1, 0, 0], [3, 0, 0]],
    "collinear_middle_vertex_last": [[0, 0, 0], [3, 0, 0], [1, 0, 0]],
    "two_equal_vertices": [[0, 0, 0], [0, 0, 0], [1, 2, 0]],
    "point": [[1, 1, 1], [1, 1, 1], [1, 1, 1]],
    "sliver_1e-10": [[0, 0, 0], [2, 0, 0], [1, 1e-10, 0]],
    "sliver_1e-6": [[0, 0, 0], [2, 0, 0], [1, 1e-6, 0]],
    "needle_1e-12": [[0, 0, 0], [1, 1e-12, 0], [2, 0, 1e-12]],
}


@pytest.mark.parametrize("name", sorted(DEGENERATE))
def test_point_triangle_degenerate_vs_sampling(name):
    tri = np.array(DEGENERATE[name], dtype=float)
    rng = np.random.default_rng(2)
    pts = rng.uniform(-1.0, 4.0, (200, 3))
    pts[:50, 2] = 0.0  # points in the (near) plane of the facet
    samples = np.vstack([_sample_tri(tri)] + [_sample_seg(tri[i], tri[(i + 1) % 3])
                                               for i in range(3)])
    sampled, _ = cKDTree(samples).query(pts, k=1)
    d = g.point_triangle_distance(pts, np.broadcast_to(tri, (len(pts), 3, 3)))
    # Segment samples are max_edge / (SEG_SAMPLES - 1) apart: half that bounds
    # the gap to the nearest sample along a thin facet.
    res = _max_edge(tri) / (SEG_SAMPLES - 1)
    assert np.all(np.isfinite(d))
    assert np.all(sampled >= d - ROUND)
    assert np.all(sampled - d <= res + ROUND)


@pytest.mark.parametrize("rel", [1e-2, 1e-5, 1e-7, 1e-9, 1e-11, 0.0])
def test_point_inside_sliver_is_on_it(rel):
    # Points inside a thin facet, in its plane: the true distance is 0.
    # Projecting onto the plane errs by ~eps * L**2 / h (normal rounding);
    # the edge fallback of slivers errs by at most h/2 (half the altitude).
    # Factor 4 covers the constants; 4 * eps * L is the rounding floor.
    eps = np.finfo(float).eps
    rng = np.random.default_rng(8)
    for _ in range(40):
        q, _r = np.linalg.qr(rng.standard_normal((3, 3)))
        tri = np.array([[0, 0, 0], [1, 0, 0], [rng.uniform(0.1, 0.9), rel, 0]])
        tri = tri @ q.T + rng.standard_normal(3)
        pts = rng.dirichlet([1, 1, 1], 50) @ tri
        d = g.point_triangle_distance(pts, np.broadcast_to(tri, (50, 3, 3)))
        length = _max_edge(tri)
        h = np.linalg.norm(np.cross(tri[1] - tri[0], tri[2] - tri[0])) / length
        bound = max(min(h, 4 * eps * length**2 / max(h, 1e-300)), 4 * eps * length)
        assert d.max() <= bound


# ------------------------------------------------------ segment - segment ---

SEGMENTS = {
    "parallel_offset": ([0, 0, 0], [1, 0, 0], [0.5, 1, 0], [2, 1, 0], 1.0),
    "parallel_disjoint": ([0, 0, 0], [1, 0, 0], [2, 1, 0], [3, 1, 0], np.sqrt(2.0)),
    "collinear_overlap": ([0, 0, 0], [2, 0, 0], [1, 0, 0], [3, 0, 0], 0.0),
    "collinear_disjoint": ([0, 0, 0], [1, 0, 0], [3, 0, 0], [2, 0, 0], 1.0),
    "crossing": ([-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], 0.0),
    "skew": ([-1, 0, 0], [1, 0, 0], [0, -1, 0.5], [0, 1, 0.5], 0.5),
    "skew_clamped": ([-1, 0, 0], [1, 0, 0], [3, -1, 0.5], [3, 1, 0.5], np.hypot(2.0, 0.5)),
    "zero_length_one": ([0, 0, 0], [0, 0, 0], [-1, 2, 0], [1, 2, 0], 2.0),
    "zero_length_both": ([0, 0, 0], [0, 0, 0], [3, 4, 0], [3, 4, 0], 5.0),
    "touching_endpoints": ([0, 0, 0], [1, 1, 1], [1, 1, 1], [2, 0, 5], 0.0),
    "nearly_parallel": ([0, 0, 0], [1, 0, 0], [0, 1e-3, 1e-7], [1, -1e-3, 1e-7], 1e-7),
}


@pytest.mark.parametrize("name", sorted(SEGMENTS))
def test_segment_segment_vs_sampling(name):
    p1, q1, p2, q2, expected = (np.array(v, dtype=float) for v in SEGMENTS[name])
    d = np.sqrt(g.segment_segment_dist2(p1, q1, p2, q2))
    assert d == pytest.approx(expected, abs=ROUND)
    s1, s2 = _sample_seg(p1, q1), _sample_seg(p2, q2)
    sampled = cKDTree(s2).query(s1, k=1)[0].min()
    res = (np.linalg.norm(q1 - p1) + np.linalg.norm(q2 - p2)) / (SEG_SAMPLES - 1)
    assert d - ROUND <= sampled <= d + res
    assert np.sqrt(g.segment_segment_dist2(p2, q2, p1, q1)) == pytest.approx(d, abs=ROUND)


def test_segment_segment_random_vs_sampling():
    rng = np.random.default_rng(3)
    for _ in range(30):
        p1, q1, p2, q2 = rng.standard_normal((4, 3))
        d = np.sqrt(g.segment_segment_dist2(p1, q1, p2, q2))
        sampled = cKDTree(_sample_seg(p2, q2)).query(_sample_seg(p1, q1), k=1)[0].min()
        res = (np.linalg.norm(q1 - p1) + np.linalg.norm(q2 - p2)) / (SEG_SAMPLES - 1)
        assert d - ROUND <= sampled <= d + res


# ---------------------------------------------------- segment - triangle ---

TRI = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=float)


@pytest.mark.parametrize("p, q, hit", [
    ([0.2, 0.2, -1], [0.2, 0.2, 1], True),      # pierces the interior
    ([0.2, 0.2, 0], [0.2, 0.2, 1], True),       # endpoint on the face
    ([0.5, 0, -1], [0.5, 0, 1], True),          # through an edge
    ([0, 0, -1], [0, 0, 1], True),              # through a vertex
    ([0.8, 0.8, -1], [0.8, 0.8, 1], False),     # misses beside the hypotenuse
    ([0.2, 0.2, 0.1], [0.2, 0.2, 1], False),    # stops short of the plane
    ([-1, 0.2, 0], [2, 0.2, 0], False),         # coplanar: left to distances
])
def test_segment_triangle_intersect(p, q, hit):
    p, q = np.array(p, dtype=float), np.array(q, dtype=float)
    assert g.segment_triangle_intersect(p, q, *TRI) is hit
    assert g.segment_triangle_intersect(q, p, *TRI) is hit


# --------------------------------------------------- triangle - triangle ---

def _tri(*rows):
    return np.array(rows, dtype=float)


A = _tri([0, 0, 0], [1, 0, 0], [0, 1, 0])
BIG = _tri([-1, -1, 0], [2, -1, 0], [-1, 2, 0])

#: name -> (a, b, exact distance in closed form, or None if only sampled)
ADVERSARIAL = {
    "parallel_offset": (A, A + [0.1, 0.1, 0.5], 0.5),
    "touching_at_edge": (A, _tri([0.2, 0, 0], [0.8, 0, 0], [0.5, -0.3, 1]), 0.0),
    "vertex_on_face": (A, _tri([0.2, 0.2, 0], [1, 1, 1], [0, 1, 1]), 0.0),
    "touching_at_vertex": (A, _tri([1, 0, 0], [2, 0, 1], [2, 1, -1]), 0.0),
    "sharing_edge": (A, _tri([0, 0, 0], [1, 0, 0], [0.5, -0.5, 0.7]), 0.0),
    "piercing": (A, _tri([0.2, 0.2, -0.5], [0.3, 0.2, 0.5], [0.25, 0.3, 0.5]), 0.0),
    "pierced_by": (_tri([0.2, 0.2, -0.5], [0.3, 0.2, 0.5], [0.25, 0.3, 0.5]), A, 0.0),
    "edges_interlocked": (A, _tri([0.3, 0.3, -0.5], [0.3, 0.3, 0.5], [2, 2, 0.2]), 0.0),
    "coplanar_overlap": (A, A + [0.2, 0.2, 0], 0.0),
    "coplanar_contained": (A, _tri([0.1, 0.1, 0], [0.2, 0.1, 0], [0.1, 0.2, 0]), 0.0),
    "coplanar_disjoint": (A, A + [2, 0, 0], 1.0),
    "far_apart": (A, _tri([10, 20, 30], [11, 20, 31], [10, 22, 29]), None),
    "edge_over_face": (BIG, _tri([0.2, -0.5, 0.1], [0.2, 0.5, 0.1], [0.2, 0, 1]), 0.1),
    "skew_edges": (_tri([-1, 0, 0], [1, 0, 0], [0, -1, -1]),
                   _tri([0, -1, 0.3], [0, 1, 0.3], [0.3, 0, 1.5]), 0.3),
    "degenerate_piercing": (A, _tri([0.2, 0.2, -1], [0.2, 0.2, 0], [0.2, 0.2, 1]), 0.0),
    "degenerate_near": (A, _tri([0.2, 0.2, 0.5], [0.2, 0.2, 1], [0.2, 0.2, 2]), 0.5),
}


@pytest.mark.parametrize("name", sorted(ADVERSARIAL))
def test_triangle_triangle_adversarial(name):
    a, b, expected = ADVERSARIAL[name]
    exact = _check_against_sampling(a, b)
    if expected is not None:
        assert exact == pytest.approx(expected, abs=ROUND)
    assert _exact(b, a) == pytest.approx(exact, abs=ROUND)
    dmin, dmin_v, dmax = g.triangle_pair_bounds(np.stack([a, b]), [0], [1])
    assert dmin[0] == pytest.approx(exact, abs=ROUND)
    assert dmin_v[0] >= dmin[0] - ROUND
    assert dmax[0] >= dmin_v[0]


def test_vertex_only_minimum_is_wrong_somewhere():
    # Paper erratum 4: the 9 vertex-vertex distances overestimate the minimum.
    gaps = {}
    for name, (a, b, _) in ADVERSARIAL.items():
        dmin, dmin_v, _ = g.triangle_pair_bounds(np.stack([a, b]), [0], [1])
        gaps[name] = dmin_v[0] - dmin[0]
    assert gaps["edge_over_face"] > 0.5
    assert gaps["piercing"] > 0.5
    assert gaps["skew_edges"] > 0.5


def test_triangle_triangle_random_vs_sampling():
    rng = np.random.default_rng(4)
    n_touch = 0
    for _ in range(150):
        a = rng.standard_normal((3, 3))
        b = rng.standard_normal((3, 3)) + rng.uniform(0.0, 1.5) * rng.standard_normal(3)
        n_touch += _check_against_sampling(a, b) == 0.0
    assert 0 < n_touch < 150  # both intersecting and separated pairs were drawn


# ---------------------------------------------------------- pair bounds ---

def _pair_setup(seed, m, p):
    rng = np.random.default_rng(seed)
    tris = rng.random((m, 1, 3)) + 0.1 * rng.standard_normal((m, 3, 3))
    return tris, rng.integers(0, m, p), rng.integers(0, m, p)


def test_pair_bounds_match_scalar_and_bruteforce():
    tris, k, l = _pair_setup(5, 60, 3000)
    dmin, dmin_v, dmax = g.triangle_pair_bounds(tris, k, l)
    vv = np.linalg.norm(tris[k][:, :, None, :] - tris[l][:, None, :, :], axis=-1)
    np.testing.assert_allclose(dmin_v, vv.min(axis=(1, 2)), rtol=0, atol=1e-12)
    np.testing.assert_allclose(dmax, vv.max(axis=(1, 2)), rtol=0, atol=1e-12)
    ref = np.array([_exact(tris[i], tris[j]) for i, j in zip(k[:500], l[:500])])
    np.testing.assert_allclose(dmin[:500], ref, rtol=0, atol=1e-12)
    assert np.all(dmin_v >= dmin)
    assert np.all(dmin[k == l] == 0.0)
    assert np.any(dmin_v - dmin > 0.05)
    v_only = g.triangle_pair_vertex_bounds(tris, k, l)
    np.testing.assert_array_equal(v_only[0], dmin_v)
    np.testing.assert_array_equal(v_only[1], dmax)


def test_pair_bounds_empty():
    out = g.triangle_pair_bounds(np.zeros((2, 3, 3)), np.zeros(0, int), np.zeros(0, int))
    assert all(x.shape == (0,) for x in out)


# ------------------------------------------------------------- validation ---

@pytest.mark.parametrize("call, match", [
    (lambda: g.point_triangle_distance(np.zeros((4, 2)), np.zeros((4, 3, 3))),
     r"points has shape \(4, 2\), expected \(n, 3\)"),
    (lambda: g.point_triangle_distance(np.zeros((4, 3)), np.zeros((4, 3))),
     r"triangles has shape \(4, 3\), expected \(n, 3, 3\)"),
    (lambda: g.closest_points_on_triangles(np.zeros((4, 3)), np.zeros((5, 3, 3))),
     "points has 4 rows and triangles 5"),
    (lambda: g.point_triangle_distance([[0, 0, np.nan]], np.zeros((1, 3, 3))),
     "NaN"),
    (lambda: g.triangle_pair_bounds(np.zeros((3, 3)), [0], [1]),
     r"triangles has shape \(3, 3\), expected \(n, 3, 3\)"),
    (lambda: g.triangle_pair_bounds(np.zeros((3, 3, 3)), [[0]], [1]),
     r"k has shape \(1, 1\), expected \(p,\)"),
    (lambda: g.triangle_pair_bounds(np.zeros((3, 3, 3)), [0.0], [1]),
     "k has dtype float64, expected integers"),
    (lambda: g.triangle_pair_bounds(np.zeros((3, 3, 3)), [0], [3]),
     r"l has values in \[3, 3\], expected indices in \[0, 3\)"),
    (lambda: g.triangle_pair_bounds(np.zeros((3, 3, 3)), [-1], [0]),
     "k has values in"),
    (lambda: g.triangle_pair_vertex_bounds(np.zeros((3, 3, 3)), [0, 1], [0]),
     "k has 2 entries and l 1"),
])
def test_bad_input_raises(call, match):
    with pytest.raises(ContactPoseError, match=match):
        call()
