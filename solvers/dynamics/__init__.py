"""Integrators and compiled per-sample kernels shared by every time-domain method."""
