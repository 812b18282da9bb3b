"""Fusion: consensus weights, fusion strategies (consensus, and on a faulty network), aggregation of GP experts,
consensus on sufficient statistics."""
