"""Reference twins of the library's fast paths: exhaustive scans, no cleverness.

Each function here answers the same question as a fast path in contactpose by brute
force, so the tests can hold the two equal.
"""

from __future__ import annotations

import numpy as np

from contactpose.model.table import query_limits
from contactpose.search.pairs import _contains


def brute_force_tuples(S, n, m):
    """Twin of the tree: test every one of the m**n tuples against every S_ij. Small m only."""
    grid = np.stack(np.meshgrid(*[np.arange(m)] * n, indexing="ij"), axis=-1).reshape(-1, n)
    keep = np.ones(len(grid), dtype=bool)
    for (i, j) in S:
        keep &= _contains(S, i, j, grid[:, i], grid[:, j])
    return grid[keep]


def brute_force_pairs(table, distance, angle, sigma_distance, sigma_angle, bounds="exact"):
    """Twin of ``PairTable.query``: the exact interval test over every stored pair."""
    lo_d, hi_d, lo_a, hi_a = query_limits(distance, angle, sigma_distance, sigma_angle)
    f = table.features
    ok = (f.dmax >= lo_d) & (f.dmin(bounds) <= hi_d) & (f.alpha_upper >= lo_a) & (f.alpha <= hi_a)
    return np.flatnonzero(ok)
