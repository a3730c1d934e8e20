"""Simulation of a fitted model and validation against records (MATLAB compare)."""
