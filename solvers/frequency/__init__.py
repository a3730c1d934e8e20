"""Frequency-response fitting of transfer-function models (optionally inside a known feedback loop)."""
from greyfit.solvers.frequency.fit import fit_frequency_response

__all__ = ["fit_frequency_response"]
