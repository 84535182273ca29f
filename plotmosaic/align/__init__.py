"""Pairwise registration: ForestAlign (structural-complexity levels + incremental ICP) and a global coarse stage."""
