"""Simulation: scenarios, ground truth, sensors and the communication network."""
