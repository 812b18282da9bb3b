"""Fusion: consensus weights, fusion strategies (consensus and faults), aggregation of GP experts,
consensus on sufficient statistics."""
