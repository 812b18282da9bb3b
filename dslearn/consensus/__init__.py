"""Consensus weights and fusion strategies."""
