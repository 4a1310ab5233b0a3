"""What a model build will need, known before any pair is listed, and the refusal if it will not fit.

The counts come from the facets and patches alone: without a span, every pair (v(v+1)/2 of v
items); with a span L, the pairs whose bounding spheres come within L, estimated from the
KD-tree ball counts of a sample of rows (:meth:`NearPairs.count_estimate`: no listing, no m²
scan). Bytes per pair are :func:`contactpose.model.table.estimate_bytes`. A build that does
not fit is refused in one line that names a span that would fit (:meth:`PairPlan.suggest_span`).
"""

from __future__ import annotations

import numpy as np

from contactpose.model.features import NearPairs
from contactpose.model.memory import budget, check_fits
from contactpose.model.patches import patch_spheres
from contactpose.model.table import estimate_bytes

#: Rescaling steps of :meth:`PairPlan.suggest_span`, and the fill of the budget that ends them.
SUGGEST_STEPS = 6
SUGGEST_FILL = 0.5
#: Each step aims at this fraction of the limit.
SUGGEST_AIM = 0.8
#: Without a span, the search for one starts at this fraction of the bounding-box diagonal.
SUGGEST_START = 0.05


class PairPlan:
    """Estimated pair counts and build memory of one mesh's tables.

    triangles : (m, 3, 3) float; valid : (m,) bool; patches : Patches or None (None, or
    ``serves`` False: no patch table); keep : callable(facet pair count) -> bool, whether the
    facet table is kept (ObjectModel's facet_pairs rule).
    """

    def __init__(self, triangles, valid, patches, serves, keep):
        self.triangles, self.valid_idx, self.keep = triangles, np.flatnonzero(valid), keep
        self.patches = patches if serves else None
        self._near, self._counts = {}, {}

    def facet_pairs(self, span):
        """Unordered valid facet pairs the facet table holds at span (None: all)."""
        return self._count("facets", len(self.valid_idx), span)

    def patch_pairs(self, span):
        """Candidate patch pairs at span (None: all; 0 without a patch table)."""
        return 0 if self.patches is None else self._count("patches", self.patches.count, span)

    def _count(self, kind, n, span):
        if span is None:
            return n * (n + 1) // 2
        if (kind, span) not in self._counts:
            self._counts[kind, span] = self._tree(kind).count_estimate(span)
        return self._counts[kind, span]

    def counts(self, span):
        """(facet pairs kept, patch pairs) at span: the facet count is 0 when the table is dropped."""
        facets = self.facet_pairs(span)
        return (facets if self.keep(facets) else 0), self.patch_pairs(span)

    def need(self, span):
        """Estimated peak bytes of the build at span."""
        return estimate_bytes(*self.counts(span))

    def check(self, num_facets, span, counts=None, extra=0):
        """Refuse a build at span that will not fit; counts : (facet pairs, patch pairs) when
        known exactly, else estimated; extra : bytes the build will also allocate (mesh-level
        steps still to come). Returns the estimated bytes."""
        facets, patch = self.counts(span) if counts is None else counts
        need = estimate_bytes(facets, patch) + extra
        if need > budget():
            what = f"the pair table for {num_facets:,} facets ({facets:,} facet pairs, {patch:,} patch pairs)"
            check_fits(need, what, self._advice(span, extra))
        return need

    def _advice(self, span, extra):
        fit = self.suggest_span(budget() - extra, span)
        if fit is None:
            return "decimate the mesh (no --max-span makes it fit)"
        return f"decimate the mesh or set --max-span {np.format_float_positional(fit, trim='-')}"

    def suggest_span(self, limit, span=None):
        """A span at which the estimated need fits in limit bytes, or None.

        Pairs of a surface within reach L + w (w: mean plus largest item radius) grow about as
        the area (L + w)²; starting from span (or SUGGEST_START of the bounding-box diagonal),
        each step rescales L + w by √(limit / need(L)), at most SUGGEST_STEPS times, until a
        span fits with at least SUGGEST_FILL of limit; the largest span that fits is returned,
        rounded down to two significant digits.
        """
        w = self._reach_width()
        size = float(np.linalg.norm(np.ptp(self.triangles.reshape(-1, 3), axis=0)))
        L, best = (SUGGEST_START * size if span is None else span), None
        if limit <= 0:
            return None
        for _ in range(SUGGEST_STEPS):
            need = self.need(L)
            if need <= limit:
                best = L if best is None else max(best, L)
                if need >= SUGGEST_FILL * limit:
                    break
            ratio = SUGGEST_AIM * limit / need  # aim below the limit: the estimates are not exact
            L = max((L + w) * np.sqrt(ratio) - w, 0.5 * L * ratio)
        return None if best is None else _round_down(best)

    def _reach_width(self):
        near = self._tree("patches" if self.patches is not None else "facets")
        return float(near.radii.mean() + near.radii.max())

    def _tree(self, kind):
        if kind not in self._near:
            if kind == "facets":
                self._near[kind] = NearPairs.of_facets(self.triangles, self.valid_idx, 0.0)
            else:
                self._near[kind] = NearPairs(*patch_spheres(self.triangles, self.patches), 0.0)
        return self._near[kind]


def _round_down(x):
    """x rounded down to two significant digits."""
    digits = 1 - int(np.floor(np.log10(x)))
    return float(np.floor(x * 10.0**digits) / 10.0**digits) if digits >= 0 else float(np.floor(x / 10.0**-digits) * 10.0**-digits)
