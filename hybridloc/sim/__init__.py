"""Simulator: buildings, walkers, IMU and radio measurements with ground truth (explicit numpy Generators)."""
