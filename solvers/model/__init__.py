"""The user's model compiled: whitelist expressions, CasADi functions, parameter layout, constraints."""
