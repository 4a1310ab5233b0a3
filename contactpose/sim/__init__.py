"""Simulation: built-in objects, simulated grasps and sensor noise, a range scanner."""
