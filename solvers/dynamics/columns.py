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

import _ctypes
import ctypes
import threading
import weakref
from collections import OrderedDict
from typing import Callable

import casadi as ca
import numpy as np

from greyfit.solvers.dynamics.compiled import builds_ended, library, max_loaded
from greyfit.solvers.dynamics.function_cache import FunctionCache
from greyfit.solvers.dynamics.quick import goes_first, pays, quick_library

# POSIX's dlclose; elsewhere a library stays loaded once loaded (as before the bound)
_dlclose: Callable[[int], None] | None = getattr(_ctypes, "dlclose", None)

# The libraries loaded through ctypes, bounded like the compiled Functions (`compiled.max_loaded`,
# GREYFIT_COMPILED_IN_MEMORY): past the bound the least recently used leaves this table. A driver (a
# ctypes function pointer) holds its library object, so a library left out is closed (dlclose) when
# the last Columns or Fold using it is gone, never while one can still call it; asked for meanwhile,
# the same open library is taken back into the table.
_libraries: "OrderedDict[str, ctypes.CDLL]" = OrderedDict()    # most recently used last
_open: "weakref.WeakValueDictionary[str, ctypes.CDLL]" = weakref.WeakValueDictionary()
_lock = threading.Lock()

# Samples per interpreted map or mapaccum of a long record (`Columns`, `Fold`). Building a mapaccum
# costs time in proportion to its length and to the Function's size (53 ms for 1 000 samples of the
# seat model's single-shooting kernel): at this length one Function serves every record longer than
# it, and a first fit builds a quarter as much
FOLD_CHUNK = 256


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
        # the compiled loop carries output 0 into input 0 as it stands: with another sparsity it
        # would read the next state from the wrong places, so only the interpreter accumulates it
        self._carries_as_is = fn.n_in() > 0 and fn.n_out() > 0 and fn.sparsity_in(0) == fn.sparsity_out(0)
        self._stand_in: int | None = None   # on the quick tier's library: `builds_ended` when it was loaded
        self._instructions = fn.n_instructions() if self._dense_inputs else 0
        self._work = self._instructions * evaluations   # interpreted (and expected) instructions
        self._find_library(evaluations)

    def _find_library(self, evaluations: float = 0.0, n: int = 0) -> None:
        # asked again while missing: a library compiled in the background is picked up when ready;
        # meanwhile the quick tier's (quick.py), once the interpreted work would cost more
        if not self._dense_inputs or (self._stand_in is not None and self._stand_in == builds_ended()):
            return
        ended = builds_ended()
        quick = None
        if self._driver is None and goes_first(self.fn):
            # quick.py first: its source is then there for gcc's background build to take
            self._work += self._instructions * n
            quick = quick_library(self.fn) if pays(self._instructions, self._work) else None
        path = library(self.fn, evaluations)
        if path is not None:
            self._driver, self._stand_in = _driver(str(path), self.fn.name()), None
        elif quick is not None:
            self._driver, self._stand_in = _driver(str(quick), self.fn.name()), ended
        elif self._driver is not None:
            self._stand_in = ended

    @property
    def compiled(self) -> bool:
        """Whether the compiled sample loop is in use (False: CasADi's map evaluates).

        Returns
        -------
        bool
            True once the Function's compiled library has been loaded through ctypes.
        """
        return self._driver is not None

    def ready(self) -> bool:
        """Whether the compiled loop is in use, after looking again for a library built meanwhile.

        Returns
        -------
        bool
            True once the library is loaded (never where compiling is off or impossible).
        """
        if self._driver is None or self._stand_in is not None:
            self._find_library()
        return self._driver is not None

    def __call__(self, *args, n: int, accumulate: bool = False) -> list[np.ndarray]:
        if self._driver is None or self._stand_in is not None:
            self._find_library(n=n)
        if self._driver is None or (accumulate and not self._carries_as_is):
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
        if n > FOLD_CHUNK and all(self.fn.sparsity_in(i).is_dense() for i in range(self.fn.n_in())):
            return [self._dense(v, j, n) for j, v in enumerate(self._chunked(args, n, accumulate))]
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

    def _chunked(self, args, n: int, accumulate: bool) -> list[np.ndarray]:
        """The outputs' nonzeros over n samples, evaluated FOLD_CHUNK samples at a time (a mapaccum of
        a long record costs time and memory in proportion to its length to build); an accumulated
        state goes from the last sample of one chunk to the first of the next."""
        flat = [np.asarray(a, dtype=float).ravel(order="F") for a in args]
        per_sample = [a.size == self._nnz_in[i] * n and not (accumulate and i == 0) for i, a in enumerate(flat)]
        parts: list[list[np.ndarray]] = [[] for _ in self._nnz_out]
        state = flat[0]
        into = carry_index(self.fn) if accumulate and n > FOLD_CHUNK else None
        for start in range(0, n, FOLD_CHUNK):
            m = min(FOLD_CHUNK, n - start)
            fm = self._maps.get((m, accumulate), lambda m=m: self.fn.mapaccum(m) if accumulate else self.fn.map(m))
            full = []
            for i, a in enumerate(flat):
                rows = self._nnz_in[i]
                if accumulate and i == 0:
                    full.append(state if start == 0 else _carried(self.fn, into, state))
                elif per_sample[i]:
                    full.append(a[start * rows:(start + m) * rows])
                else:
                    full.append(np.tile(a, m))
            outs = nonzeros(fm, full)
            if accumulate:
                state = outs[0][-self._nnz_out[0]:]
            for part, o in zip(parts, outs):
                part.append(o)
        return [np.concatenate(part) for part in parts]


def carry_index(fn: ca.Function) -> np.ndarray | None:
    """Where each nonzero of output 0 (a sample's next state) lies among input 0's nonzeros (the next
    sample's state): a sensitivity that is structurally zero leaves a sparse output (17 of 24 entries
    for a difference equation's delay states) where the input is dense. None where the two
    sparsities are one.

    Parameters
    ----------
    fn : casadi.Function
        The per-sample Function.

    Returns
    -------
    numpy.ndarray or None
        Positions among input 0's nonzeros, one per nonzero of output 0.
    """
    sp_in, sp_out = fn.sparsity_in(0), fn.sparsity_out(0)
    if sp_in == sp_out:
        return None
    place = {rc: k for k, rc in enumerate(zip(*sp_in.get_triplet()))}
    return np.array([place[rc] for rc in zip(*sp_out.get_triplet())], dtype=int)


def _carried(fn: ca.Function, into: np.ndarray | None, state: np.ndarray) -> np.ndarray:
    if into is None:
        return state
    out = np.zeros(fn.nnz_in(0))
    out[into] = state
    return out


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


def _load_library(path: str) -> ctypes.CDLL:
    """The library at `path`, loaded once while anything holds it, and now the most recently used."""
    with _lock:
        lib = _libraries.pop(path, None)
        if lib is None:
            lib = _open.get(path)
        if lib is None:
            lib = _open[path] = ctypes.CDLL(path)
            if _dlclose is not None:
                # when the object goes (out of the table, no driver left): nothing can call into it
                weakref.finalize(lib, _dlclose, lib._handle).atexit = False
        _libraries[path] = lib
        while len(_libraries) > max_loaded():
            _libraries.popitem(last=False)
    return lib


def _driver(path: str, name: str, kind: str = "columns"):
    # lib[name], not getattr: getattr keeps the function on the library object too (a cycle that
    # only the garbage collector would break)
    fn = _load_library(path)[f"greyfit_{kind}_{name}"]
    if kind == "columns":
        fn.argtypes = [ctypes.c_longlong, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
                       ctypes.c_int]
    else:
        fn.argtypes = [ctypes.c_longlong, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
    fn.restype = ctypes.c_int
    return fn


class Fold:
    """`fn` folded over n samples in one call: output 0 of sample k is input 0 of sample k+1 and
    the other outputs are summed over the samples, except those in `per_sample`, which are kept
    for every sample (the compiled library's `greyfit_fold_` loop, else CasADi's `mapaccum`, with
    the same results).

    Inputs as for `Columns` with `accumulate`: input 0 is the first sample's state, the others
    (rows, n) per sample or (rows,) shared. Returns the state after the last sample, then per
    output its sum, or for a `per_sample` output its nonzeros at every sample (sample k's at
    k·nnz .. (k+1)·nnz − 1), each flat.
    """

    def __init__(self, fn: ca.Function, evaluations: float = 0.0, interpret_meanwhile: bool = False,
                 per_sample: tuple[int, ...] = ()):
        """`interpret_meanwhile`: never wait for gcc (a missing library is built in the background
        and the fold switches to it at its first call after the build has ended); `per_sample`:
        the outputs (≥ 1) kept per sample rather than summed."""
        if any(j < 1 or j >= fn.n_out() for j in per_sample):
            raise ValueError(f"per_sample outputs of {fn.name()} must be among 1 .. {fn.n_out() - 1}")
        self.fn = fn
        self.per_sample = frozenset(per_sample)
        self._interpret_meanwhile = interpret_meanwhile
        self._maps = FunctionCache(4)
        self._driver = None
        self._nnz_in = [fn.nnz_in(i) for i in range(fn.n_in())]
        self._nnz_out = [fn.nnz_out(j) for j in range(fn.n_out())]
        self._evaluations = evaluations
        self._stand_in: int | None = None   # as `Columns`
        self.find_library()

    def find_library(self, evaluations: float | None = None) -> bool:
        """Load the compiled loop if its library is ready (built now, on disk, or finished in the
        background since the last call).

        Parameters
        ----------
        evaluations : float or None, optional
            Expected evaluations from now on (whether a compile in the foreground pays); None
            keeps the last estimate.

        Returns
        -------
        bool
            Whether the compiled loop is in use.
        """
        if evaluations is not None:
            self._evaluations = evaluations
        # the compiled loop carries output 0 into input 0 as it stands (see `Columns`)
        carries_as_is = self.fn.sparsity_in(0) == self.fn.sparsity_out(0)
        looks = self._driver is None or (self._stand_in is not None and self._stand_in != builds_ended())
        if looks and self.fn.is_a("SXFunction") and carries_as_is:
            ended = builds_ended()
            quick = None
            if self._driver is None and goes_first(self.fn):
                # quick.py, until gcc's library is ready, where the expected interpreted work pays for
                # it; first, so that its source is there for gcc's background build to take
                instructions = self.fn.n_instructions()
                quick = quick_library(self.fn) if pays(instructions, instructions * self._evaluations) else None
            path = library(self.fn, self._evaluations, self._interpret_meanwhile)
            if path is not None:
                self._driver, self._stand_in = _driver(str(path), self.fn.name(), "fold"), None
            elif quick is not None:
                self._driver, self._stand_in = _driver(str(quick), self.fn.name(), "fold"), ended
            elif self._driver is not None:
                self._stand_in = ended
        return self._driver is not None

    @property
    def compiled(self) -> bool:
        """Whether the compiled loop is in use (False: CasADi's mapaccum evaluates).

        Returns
        -------
        bool
            True once the Function's library has been loaded through ctypes.
        """
        return self._driver is not None

    def __call__(self, *args: np.ndarray, n: int) -> list[np.ndarray]:
        if self._driver is None or self._stand_in is not None:
            self.find_library()
        if self._driver is None:
            return self._casadi(args, n)
        strides = [0] + [self._nnz_in[i] if a.size == self._nnz_in[i] * n and n > 1 else 0
                         for i, a in enumerate(args) if i]
        outputs = self._outputs(n)
        arg = (ctypes.c_void_p * len(args))(*[a.ctypes.data for a in args])
        res = (ctypes.c_void_p * len(outputs))(*[o.ctypes.data for o in outputs])
        astride = (ctypes.c_longlong * len(strides))(*strides)
        if self._driver(n, arg, astride, res, self._rstride()):
            raise RuntimeError(f"evaluation of {self.fn.name()} failed")
        return outputs

    def _outputs(self, n: int) -> list[np.ndarray]:
        return [np.empty(nnz * n if j in self.per_sample else nnz) for j, nnz in enumerate(self._nnz_out)]

    def _rstride(self):
        return (ctypes.c_longlong * len(self._nnz_out))(
            *[nnz if j in self.per_sample else 0 for j, nnz in enumerate(self._nnz_out)])

    def bind(self, args: list[np.ndarray], n: int) -> "BoundFold":
        """This fold over fixed input buffers, for repeated calls whose inputs change in place.

        Parameters
        ----------
        args : list of numpy.ndarray
            One array per input, as for a call; flat float arrays are used as they are (not copied),
            so rewriting one rewrites the input.
        n : int
            The number of samples.

        Returns
        -------
        BoundFold
            Its `args` are the buffers to rewrite between calls.
        """
        return BoundFold(self, args, n)

    def _casadi(self, args, n: int) -> list[np.ndarray]:
        # CasADi's mapaccum(n) costs time and memory in proportion to n to build (1.5 s and 330 MB
        # for 200 000 samples of a small sensitivity step, the peak of a long record's first fit):
        # chunks of FOLD_CHUNK samples, the state carried from one to the next, cost neither
        flat = [np.asarray(a, dtype=float).ravel(order="F") for a in args]
        per_sample = [i > 0 and a.size == self._nnz_in[i] * n and n > 1 for i, a in enumerate(flat)]
        state, sums = flat[0], [np.zeros(nnz) for nnz in self._nnz_out[1:]]
        kept: dict[int, list[np.ndarray]] = {j: [] for j in self.per_sample}
        into = carry_index(self.fn) if n > FOLD_CHUNK else None
        for start in range(0, n, FOLD_CHUNK):
            m = min(FOLD_CHUNK, n - start)
            fm = self._maps.get((m,), lambda m=m: self.fn.mapaccum(m))
            full = [state if start == 0 else _carried(self.fn, into, state)]
            for i, a in enumerate(flat[1:], 1):   # the map repeats a shared input; its buffer wants every copy
                rows = self._nnz_in[i]
                full.append(a[start * rows:(start + m) * rows] if per_sample[i]
                            else np.tile(a, fm.nnz_in(i) // max(a.size, 1)))
            outs = nonzeros(fm, full)
            state = outs[0][-self._nnz_out[0]:]
            # the running sums as the first row, added one row after another, the compiled loop's
            # order, so both give the same numbers to the last bit: a cumulative sum (np.add.reduce
            # sums a single column pairwise: a one-number output such as the cost came out an ulp apart)
            for j in self.per_sample:
                kept[j].append(outs[j])
            sums = [total if j in self.per_sample
                    else np.cumsum(np.vstack([total, o.reshape(m, total.size)]), axis=0)[-1]
                    for j, (total, o) in enumerate(zip(sums, outs[1:]), 1)]
        return [state] + [np.concatenate(kept[j]) if j in self.per_sample else total
                          for j, total in enumerate(sums, 1)]


class BoundFold:
    """A `Fold` whose input buffers and C argument arrays are made once: a call costs the loop
    and a few microseconds (building ctypes arrays per call took longer than a short record's
    compiled work). Rewrite `args[i][:]` in place between calls (flat float arrays given are used
    as they are, so two bound folds may share a record); the outputs are fresh arrays, or with
    ``copy=False`` the fold's own buffers, valid until its next call."""

    def __init__(self, fold: Fold, args: list[np.ndarray], n: int):
        self.fold, self.n = fold, n
        # the arrays themselves where they already are flat float buffers (no copy of a long record)
        self.args = [np.ascontiguousarray(np.asarray(a, dtype=float).ravel(order="F")) for a in args]
        self._c: tuple | None = None

    def _c_arrays(self) -> tuple:
        fold, args, n = self.fold, self.args, self.n
        strides = [0] + [fold._nnz_in[i] if a.size == fold._nnz_in[i] * n and n > 1 else 0
                         for i, a in enumerate(args) if i]
        outputs = fold._outputs(n)
        return (outputs, (ctypes.c_void_p * len(args))(*[a.ctypes.data for a in args]),
                (ctypes.c_longlong * len(strides))(*strides),
                (ctypes.c_void_p * len(outputs))(*[o.ctypes.data for o in outputs]), fold._rstride())

    def __call__(self, copy: bool = True) -> list[np.ndarray]:
        fold = self.fold
        if (fold._driver is None or fold._stand_in is not None) and not fold.find_library():
            return fold._casadi(self.args, self.n)
        if self._c is None:
            self._c = self._c_arrays()
        outputs, arg, astride, res, rstride = self._c
        driver = fold._driver
        if driver is None or driver(self.n, arg, astride, res, rstride):
            raise RuntimeError(f"evaluation of {fold.fn.name()} failed")
        return [o.copy() for o in outputs] if copy else outputs
