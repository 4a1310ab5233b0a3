"""The offline phase: mesh -> facet planes -> pair features -> patches -> the table K3.

Paper equations:

* eq. (2), the facet planes n_k, d_k (made unit, erratum 1) -> :func:`object_model.facet_planes`;
* §3.1, the pair characteristics Δmin, Δmax, α (exact Δmin, erratum 4) -> :func:`features.pair_features`;
* eq. (3), the bins' widths, and eq. (4), the hash functions t1, t2, t3 (clamped, erratum 2)
  -> :class:`table.PairTable`, :func:`table.bin_index`;
* eq. (5), the union of admissible bins (∪ for ∩, erratum 2) -> :meth:`table.PairTable.query`
  (called by search.pairs.admissible_pairs).
"""

from contactpose.model.object_model import FacetPlanes, ObjectModel, facet_planes, load_mesh, merged_mesh
from contactpose.model.symmetry import Symmetry, symmetries

__all__ = ["FacetPlanes", "ObjectModel", "Symmetry", "facet_planes", "load_mesh", "merged_mesh", "symmetries"]
