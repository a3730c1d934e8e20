"""Uncertainty: Jacobian covariance, HAC, profile likelihood, small statistics."""
