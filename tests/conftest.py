"""Suite-wide settings: the interpreted CasADi path unless a test asks for compiled C.

Compiling every test model's functions with gcc would cost more than it saves on the short records
the tests use; tests/solvers/test_compiled.py runs the compiled path and compares it with this one.
"""
import os

os.environ.setdefault("GREYFIT_COMPILE", "never")
