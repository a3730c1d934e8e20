"""The least-squares NLP every method builds, and its Ipopt solvers."""
