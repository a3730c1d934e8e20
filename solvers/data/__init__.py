"""Measured records turned into arrays: checks, windows, detrending, derivatives, prefilters."""
