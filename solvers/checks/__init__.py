"""Trust checks: excitation before the fit, residual diagnostics and the quality verdict after it."""
