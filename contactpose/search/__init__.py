"""The online search: pair conditions and S_ij (eq. 5), joined into hypotheses by the tree T (§3.2)."""
