"""Simulation: world generator, renderer, trajectories, sensors, dataset writer."""
