"""Simulation: scenarios, ground truth, sensors, placing the communication network, faults drawn on episodes."""
