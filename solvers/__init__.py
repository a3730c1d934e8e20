"""Numerics of greyfit: expression compiler, problem builders, covariance, diagnostics."""
from greyfit.solvers.errors import CovarianceUnavailable, DataError, FitError, ModelDefinitionError

__all__ = ["FitError", "ModelDefinitionError", "DataError", "CovarianceUnavailable"]
