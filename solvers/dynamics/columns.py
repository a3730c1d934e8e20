"""A per-sample Function evaluated over the columns of numpy arrays, for numbers (not graphs).

`fn.map(n)(...)` returns CasADi matrices, and turning those into numpy costs ~100 ns per number
(CasADi builds a Python list): 9 ms for the 8000 × 8 equation-error Jacobian of the seat model,
where evaluating it takes 0.1 ms. Where the Function is compiled (solvers/dynamics/compiled.py), its library
carries a loop over samples that reads and writes numpy buffers directly; it is called through
ctypes. Elsewhere the CasADi map runs, with the same results in the same layout.

Layout, as `fn.map(n)` (or `mapaccum` with `accumulate`): an input is (rows, n) per sample or
(rows, 1) / (rows,) for all samples; output j is (size1_j, n · size2_j), sample k's block in columns
k·size2_j .. (k+1)·size2_j − 1, dense.
"""
from __future__ import annotations

import ctypes
import threading

import casadi as ca
import numpy as np

from greyfit.solvers.dynamics.compiled import library
from greyfit.solvers.dynamics.function_cache import FunctionCache

_libraries: dict[str, ctypes.CDLL] = {}
_lock = threading.Lock()


class Columns:
    """`fn` (dense inputs, one sample each) evaluated at n samples at once."""

    def __init__(self, fn: ca.Function, evaluations: float = 0.0, compile: bool = True):
        """`compile=False` for a Function used by one request only (a stand-in model, not a compiled one):
        a compiler run would cost more than it saves."""
        self.fn = fn
        self._maps = FunctionCache(8)
        self._driver = None
        # only SX graphs are generated as C here (an integrator such as CVODES is not)
        self._dense_inputs = compile and fn.is_a("SXFunction") and all(
            fn.sparsity_in(i).is_dense() for i in range(fn.n_in()))
        self._out_sparsity = [fn.sparsity_out(j) for j in range(fn.n_out())]
        self._nnz_in = [fn.nnz_in(i) for i in range(fn.n_in())]
        self._nnz_out = [sp.nnz() for sp in self._out_sparsity]
        self._scatters: dict[tuple[int, int], np.ndarray] = {}
        self._find_library(evaluations)

    def _find_library(self, evaluations: float = 0.0) -> None:
        # asked again while missing: a library compiled in the background is picked up when ready
        if self._dense_inputs:
            path = library(self.fn, evaluations)
            if path is not None:
                self._driver = _driver(str(path), self.fn.name())

    @property
    def compiled(self) -> bool:
        """Whether the compiled sample loop is in use (False: CasADi's map evaluates).

        Returns
        -------
        bool
            True once the Function's compiled library has been loaded through ctypes.
        """
        return self._driver is not None

    def __call__(self, *args, n: int, accumulate: bool = False) -> list[np.ndarray]:
        if self._driver is None:
            self._find_library()
        if self._driver is None:
            return self._casadi(args, n, accumulate)
        fn = self.fn
        inputs, strides = [], []
        for i, a in enumerate(args):
            a = np.asarray(a, dtype=float)
            rows = self._nnz_in[i]
            per_sample = a.size == rows * n and n > 1 and not (accumulate and i == 0)
            if not per_sample and a.size != rows:
                raise ValueError(f"input {i} of {fn.name()}: {a.shape} for {rows} rows and {n} samples")
            a = np.asfortranarray(a) if per_sample else np.ascontiguousarray(a.ravel(order="F"))
            inputs.append(a)
            strides.append(rows if per_sample else 0)
        outputs = [np.empty(nnz * n) for nnz in self._nnz_out]
        arg = (ctypes.c_void_p * max(len(inputs), 1))(*[a.ctypes.data for a in inputs])
        res = (ctypes.c_void_p * max(len(outputs), 1))(*[o.ctypes.data for o in outputs])
        astride = (ctypes.c_longlong * max(len(strides), 1))(*strides)
        rstride = (ctypes.c_longlong * max(len(outputs), 1))(*self._nnz_out)
        if n and self._driver(n, arg, astride, res, rstride, int(accumulate)):
            raise RuntimeError(f"evaluation of {fn.name()} failed")
        return [self._dense(o, j, n) for j, o in enumerate(outputs)]

    def _dense(self, values: np.ndarray, j: int, n: int) -> np.ndarray:
        """Output j's nonzeros for n samples as the dense (size1, n · size2) array."""
        sp = self._out_sparsity[j]
        r, c = sp.size1(), sp.size2()
        if sp.is_dense():
            return values.reshape((r, n * c), order="F")
        out = np.zeros(r * n * c)
        out[self._scatter(j, n)] = values
        return out.reshape((r, n * c), order="F")

    def _scatter(self, j: int, n: int) -> np.ndarray:
        """Where each nonzero of n samples goes in the dense column-major result; the same for
        every call with n samples (a fit evaluates one record several times)."""
        key = (j, n)
        cached = self._scatters.get(key)
        if cached is None:
            sp = self._out_sparsity[j]
            rows, cols = sp.get_triplet()
            one = np.asarray(rows) + sp.size1() * np.asarray(cols)
            cached = (one[None, :] + sp.numel() * np.arange(n)[:, None]).ravel()
            if len(self._scatters) >= 4:
                self._scatters.clear()
            self._scatters[key] = cached
        return cached

    def _casadi(self, args, n: int, accumulate: bool) -> list[np.ndarray]:
        fm = self._maps.get((n, accumulate), lambda: self.fn.mapaccum(n) if accumulate else self.fn.map(n))
        if not all(fm.sparsity_in(i).is_dense() for i in range(fm.n_in())):
            out = fm(*[a if not isinstance(a, np.ndarray) or a.ndim != 1 else a[:, None] for a in args])
            return [np.asarray(o.full()) for o in (out if isinstance(out, (list, tuple)) else [out])]
        full = []
        for i, a in enumerate(args):   # CasADi's map repeats a one-sample input; the buffer wants it all
            a = np.asarray(a, dtype=float)
            full.append(a.ravel(order="F") if a.size == fm.nnz_in(i)
                        else np.tile(a.ravel(order="F"), fm.nnz_in(i) // max(a.size, 1)))
        return [self._dense(v, j, n) for j, v in enumerate(nonzeros(fm, full))]


def nonzeros(fn: ca.Function, args: list[np.ndarray]) -> list[np.ndarray]:
    """The nonzeros of each output of `fn`, written by CasADi straight into numpy arrays (its
    FunctionBuffer): no DM result to convert. Inputs: dense, one number per nonzero, column-major.

    Parameters
    ----------
    fn : casadi.Function
        The Function to evaluate.
    args : list of numpy.ndarray
        One array per input of `fn`, holding exactly `fn.nnz_in(i)` numbers (flattened column-major).

    Returns
    -------
    list of numpy.ndarray
        One flat array per output of `fn`, of length `fn.nnz_out(i)`.

    Raises
    ------
    ValueError
        When an input holds a different number of values than its input's nonzeros.
    RuntimeError
        When the evaluation of `fn` fails.
    """
    buf, run = fn.buffer()   # per call: a Function's buffer is not to be shared between threads
    args = [np.ascontiguousarray(a, dtype=float).ravel(order="F") for a in args]
    for i, a in enumerate(args):
        if a.size != fn.nnz_in(i):
            raise ValueError(f"input {i} of {fn.name()}: {a.size} numbers for {fn.nnz_in(i)}")
        buf.set_arg(i, memoryview(a))  # type: ignore[arg-type]
    outs = [np.empty(fn.nnz_out(i)) for i in range(fn.n_out())]
    for i, o in enumerate(outs):
        buf.set_res(i, memoryview(o))  # type: ignore[arg-type]
    run()
    if buf.ret() != 0:
        raise RuntimeError(f"evaluation of {fn.name()} failed")
    return outs


def evaluate(fn: ca.Function, args: list[np.ndarray]) -> list[np.ndarray]:
    """`nonzeros` of a Function with dense outputs, each in its shape (converting a DM result took
    as long as evaluating it: 9 ms for the 8000 × 16 Jacobian of seed 000's seat record).

    Parameters
    ----------
    fn : casadi.Function
        A Function whose outputs are dense.
    args : list of numpy.ndarray
        One array per input, as for `nonzeros`.

    Returns
    -------
    list of numpy.ndarray
        One array per output, reshaped (column-major) to `fn.size_out(i)`.

    Raises
    ------
    ValueError, RuntimeError
        As `nonzeros`.
    """
    return [flat.reshape(fn.size_out(i), order="F") for i, flat in enumerate(nonzeros(fn, args))]


def _driver(path: str, name: str):
    with _lock:
        lib = _libraries.get(path)
        if lib is None:
            lib = _libraries[path] = ctypes.CDLL(path)
    fn = getattr(lib, f"greyfit_columns_{name}")
    fn.argtypes = [ctypes.c_longlong, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
                   ctypes.c_int]
    fn.restype = ctypes.c_int
    return fn
