"""Small CasADi Functions generated as C, compiled once per structure and cached (memory and disk).

What is compiled is the per-sample work (an integrator step with its Jacobians, an output with its
Jacobians); the NLP around it stays a CasADi graph that calls the compiled code through `map`, so
compiling costs ~1 s per model instead of the 12-25 s of JIT-compiling a whole NLP.

The cache key is a hash of the Function's serialised form (its exact expression graph), the CasADi
version and the compiler flags: two requests with the same model structure share the library,
whatever their data or parameter values. The disk cache (`GREYFIT_CACHE_DIR`, default
`~/.cache/greyfit`; the service sets it under its data directory) survives restarts and is shared by
worker processes; libraries are written to a temporary name and renamed, so a reader never loads a
half-written file, and built under a lock file, so worker processes that meet a new model at the same
moment (the first fits of a batch) run the compiler once: the others wait and load its library.

`GREYFIT_COMPILE`: `auto` (default) compiles when a C compiler is present and the expected
interpreted work is large enough to repay the compile, and otherwise compiles in the background so
the next fit of that model finds it (a failed background compile is tried again after a back-off:
1 min, doubling, at most hourly); `always` compiles whenever it can; `never` keeps the interpreter.
A caller that can go on interpreted meanwhile (`interpret_meanwhile=True`: the structured shooting
NLP, which moves to the compiled one at the start of its next solve, and the folded sample loops,
which move at their next call) never waits for gcc in `auto`: the build runs in the background
however large the work, so a first fit never waits longer than interpreting it would take (gcc took
1 s on a quiet machine, a minute on a loaded one). Compiled and interpreted give the same numbers
bit for bit (-ffp-contract=off, below), so when the build ends changes no result. `wait_for_builds` lets a
process that is about to exit (the CLI) leave the libraries it started on disk for the next one.
"""
from __future__ import annotations

import atexit
import contextlib
import functools
import hashlib
import heapq
import itertools
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from collections import OrderedDict
from collections.abc import Iterator
from pathlib import Path

import casadi as ca

try:
    import fcntl
except ImportError:   # not POSIX: no cross-process lock, at worst a library is built twice
    fcntl = None  # type: ignore[assignment]

# -Bsymbolic: the columns driver must call this library's own function, not a namesake loaded
# before it (glibc exports a legacy `step`). -O3 -march=native: per 1000 samples, seed 000's seat
# sensitivity kernel took 5.4 ms -O1, 5.2 ms -O3, 4.7 ms -O3 -march=native on a quiet machine
# (gcc itself 4.0, 6.7 and 6.5 s CPU); the target ISA then enters the cache key (`target`), so a
# library built for another CPU of a fleet sharing the cache is never loaded (`GREYFIT_NATIVE=0`:
# the compiler's default target). -ffp-contract=off: no fused multiply-adds, so the compiled
# numbers stay those of CasADi's interpreter bit for bit, on every CPU (the same speed here).
# (-O3, or -O1 for a large source: `optimisation_flags`)
CFLAGS = ["-ffp-contract=off", "-fPIC", "-shared", "-Wl,-Bsymbolic"]
# interpreted SX costs ~10 ns per instruction here; gcc ~1 s for a few thousand: compile in the
# foreground when a fit would spend more than about a second interpreting, and more than gcc would
# take. gcc's time grows with the source: ~0.3 s, and ~0.3 ms an instruction at -O1 to ~0.8 at -O3
# (the seat's 8 000-instruction sensitivity kernel 4-7 s; a 117 000-instruction row kernel of 314
# RK4 substeps 33 s at -O1, in the foreground of a fit that would have interpreted it in 1 s)
FOREGROUND_WORK = 1e8          # instructions × expected evaluations
INTERPRET_S_PER_INSTRUCTION = 1e-8
COMPILE_S, COMPILE_S_PER_INSTRUCTION = 0.3, 5e-4
COMPILE_TIMEOUT_S = 120
# generated sources above this compile at -O1, above the next not at all (`optimisation_flags`)
LARGE_SOURCE_BYTES = 1_000_000
MAX_SOURCE_BYTES = 8_000_000
# a background compile that failed (disk full, killed, out of memory) is tried again after this,
# doubled after each failure: a compiler that always fails costs one attempt per hour at most
RETRY_AFTER_S = 60.0
# a background build waits this long for a compile slot, then gives up until it is asked for again
# (a slot's holder runs one compile, which COMPILE_TIMEOUT_S bounds: a longer wait is a long queue)
SLOT_WAIT_S = COMPILE_TIMEOUT_S + 10.0
MAX_RETRY_S = 3600.0

# Appended to every library: evaluates the function at n samples, input i of sample k at
# arg[i] + k * astride[i] (stride 0: the same for every sample), output j at res[j] + k * rstride[j];
# `accumulate` feeds output 0 of sample k-1 to input 0 of sample k (mapaccum). Called through
# ctypes on numpy buffers (solvers/dynamics/columns.py): no CasADi matrices, no copies.
COLUMNS_DRIVER = r"""
#include <stdlib.h>
int greyfit_columns_FN(long long n, const double** arg, const long long* astride, double** res,
                       const long long* rstride, int accumulate) {
  casadi_int sz_arg, sz_res, sz_iw, sz_w, i, k;
  casadi_int n_in = FN_n_in(), n_out = FN_n_out();
  int flag = 0;
  FN_work(&sz_arg, &sz_res, &sz_iw, &sz_w);
  const double** a = (const double**) calloc(sz_arg + 1, sizeof(double*));
  double** r = (double**) calloc(sz_res + 1, sizeof(double*));
  casadi_int* iw = (casadi_int*) malloc((sz_iw + 1) * sizeof(casadi_int));
  double* w = (double*) malloc((sz_w + 1) * sizeof(double));
  if (!a || !r || !iw || !w) flag = 1;
  for (k = 0; k < n && !flag; ++k) {
    for (i = 0; i < n_in; ++i) a[i] = arg[i] ? arg[i] + k * astride[i] : 0;
    if (accumulate && k > 0) a[0] = res[0] + (k - 1) * rstride[0];
    for (i = 0; i < n_out; ++i) r[i] = res[i] ? res[i] + k * rstride[i] : 0;
    flag = FN(a, r, iw, w, 0);
  }
  free(a); free(r); free(iw); free(w);
  return flag;
}

/* A fold over n samples in one call: output 0 of sample k is input 0 of sample k+1 (the state,
   ping-ponged between two buffers, its final value written to res[0]); an output j >= 1 with
   rstride[j] = 0 is summed over the samples into res[j], one with rstride[j] > 0 is written per
   sample at res[j] + k * rstride[j] (not at all where res[j] is NULL). Memory stays constant in n
   where nothing is asked per sample: a simulation that reduces to a cost, a gradient and a
   Gauss-Newton Hessian writes no per-sample values. */
int greyfit_fold_FN(long long n, const double** arg, const long long* astride, double** res,
                    const long long* rstride) {
  casadi_int sz_arg, sz_res, sz_iw, sz_w, i, j, k, total = 0;
  casadi_int n_in = FN_n_in(), n_out = FN_n_out();
  casadi_int nnz[64];
  int flag = 0;
  if (n_out > 64) return 1;
  for (j = 0; j < n_out; ++j) {
    const casadi_int* sp = FN_sparsity_out(j);
    nnz[j] = sp[2] == 1 ? sp[0] * sp[1] : sp[2 + sp[1]];   /* {rows, cols, 1}: dense (CasADi's compact form) */
    total += nnz[j];
  }
  FN_work(&sz_arg, &sz_res, &sz_iw, &sz_w);
  const double** a = (const double**) calloc(sz_arg + 1, sizeof(double*));
  double** r = (double**) calloc(sz_res + 1, sizeof(double*));
  casadi_int* iw = (casadi_int*) malloc((sz_iw + 1) * sizeof(casadi_int));
  double* w = (double*) malloc((sz_w + 1) * sizeof(double));
  double* buf = (double*) malloc((total + nnz[0] + 1) * sizeof(double));
  if (!a || !r || !iw || !w || !buf) flag = 1;
  double* state[2] = {buf, buf + nnz[0]};
  double* tmp = buf + 2 * nnz[0];
  for (j = 1; j < n_out && !flag; ++j) if (!rstride[j]) for (i = 0; i < nnz[j]; ++i) res[j][i] = 0.0;
  for (k = 0; k < n && !flag; ++k) {
    for (i = 1; i < n_in; ++i) a[i] = arg[i] + k * astride[i];
    a[0] = k ? state[(k - 1) & 1] : arg[0];
    r[0] = state[k & 1];
    double* t = tmp;
    for (j = 1; j < n_out; ++j) {
      if (rstride[j]) r[j] = res[j] ? res[j] + k * rstride[j] : 0;
      else { r[j] = t; t += nnz[j]; }
    }
    flag = FN(a, r, iw, w, 0);
    for (j = 1; j < n_out; ++j) if (!rstride[j]) for (i = 0; i < nnz[j]; ++i) res[j][i] += r[j][i];
  }
  if (!flag && n > 0) for (i = 0; i < nnz[0]; ++i) res[0][i] = state[(n - 1) & 1][i];
  free(a); free(r); free(iw); free(w); free(buf);
  return flag;
}
"""

# Both caches are bounded: each distinct model structure loaded cost ~93 KB that was never given
# back, and each built library stays on disk. In memory the least recently used Function is dropped
# past MAX_LOADED (`GREYFIT_COMPILED_IN_MEMORY`); on disk the oldest libraries are deleted once the
# folder holds more than `GREYFIT_CACHE_MAX_BYTES` (default 512 MB), never one built in the last
# KEEP_RECENT_S (another process may be about to load it; a process that has loaded a library keeps
# its mapping when the file is deleted). A dropped library costs a compile, never a result.
MAX_LOADED = 128
DEFAULT_CACHE_MAX_BYTES = 512 * 1024 * 1024
KEEP_RECENT_S = 600.0

_memory: dict[str, ca.Function] = {}   # insertion order is recency: a hit moves its key to the end
_pending: set[str] = set()                      # keys compiled in the background now
_failed: dict[str, tuple[int, float]] = {}       # key -> (failures, monotonic time of the next try)
_ended = [0]   # background builds ended in this process: a loop on a stand-in library looks again when it moves
# key -> (Function, library, expected work) of each background build running here: what
# `hand_over_builds` gives a detached process when this one exits before they end
_building: dict[str, tuple[ca.Function, Path, float]] = {}
# set by `abandon_builds`: a build waiting for a slot or a lock gives up, none starts a compiler
_abandon = threading.Event()
_lock = threading.Lock()
# the compilers and source generators running for this process's builds, each the leader of its
# own process group: ended when the process exits (`_end_children`)
_children: set[subprocess.Popen] = set()


def mode() -> str:
    """The compile policy from `GREYFIT_COMPILE`.

    Returns
    -------
    str
        ``"auto"``, ``"always"`` or ``"never"``; an unset value gives ``"auto"``, and so does an
        unknown one, with a `RuntimeWarning` the first time.
    """
    value = os.environ.get("GREYFIT_COMPILE", "auto").strip().lower()
    if value in ("auto", "always", "never"):
        return value
    _unknown_setting("GREYFIT_COMPILE", value, ("auto", "always", "never"), "auto")
    return "auto"


@functools.lru_cache(maxsize=16)
def _unknown_setting(name: str, value: str, known: tuple[str, ...], used: str) -> None:
    """Say once per value that a setting is not one greyfit knows (a typo would otherwise go unseen)."""
    warnings.warn(f"{name}={value!r} is not one of {', '.join(known)}: greyfit uses {used!r}",
                  RuntimeWarning, stacklevel=3)


def cache_dir() -> Path:
    """The folder of the compiled libraries on disk.

    Returns
    -------
    pathlib.Path
        ``$GREYFIT_CACHE_DIR/compiled``, or ``~/.cache/greyfit/compiled`` when the variable is unset.
    """
    return _cache_dir(os.environ.get("GREYFIT_CACHE_DIR") or "", os.environ.get("HOME", ""))


@functools.lru_cache(maxsize=8)
def _cache_dir(asked: str, home: str) -> Path:   # asked for every Function a fit looks up (~40 a fit)
    return Path(asked or Path.home() / ".cache" / "greyfit") / "compiled"


def compiler() -> str | None:
    """The C compiler found on PATH (``$CC``, default ``gcc``); the search is cached.

    Returns
    -------
    str or None
        Full path of the compiler, or None where none is found.
    """
    return _which(os.environ.get("CC", "gcc"))


def _compiler_path() -> str:
    path = compiler()
    if path is None:   # callers check `compiler()` before building; a race with PATH changes lands here
        raise RuntimeError("no C compiler on PATH (set CC)")
    return path


@functools.lru_cache(maxsize=8)
def _which(name: str) -> str | None:   # a PATH search costs ~0.2 ms, asked on every Function
    return shutil.which(name)


def target() -> tuple[tuple[str, ...], str]:
    """(extra compiler flags, description of the instruction set they target) on this machine.

    With -march=native, the description is what native means here: the CPU's identity and
    instruction-set flags from /proc/cpuinfo (no process to start), or else the compiler's own
    account (``-march=native -Q --help=target``); without (no compiler, neither source answering,
    `GREYFIT_NATIVE=0`) it is ``"default"``.

    Returns
    -------
    flags : tuple of str
        ``("-march=native",)`` or empty.
    isa : str
        The text that identifies the target in the cache key.
    """
    cc = compiler()
    native = os.environ.get("GREYFIT_NATIVE", "1").strip() != "0"
    return _native_target(cc) if (cc is not None and native) else ((), "default")


CPU_FIELDS = ("vendor_id", "cpu family", "model", "flags", "features", "cpu implementer", "cpu part")


@functools.lru_cache(maxsize=4)
def _native_target(cc: str) -> tuple[tuple[str, ...], str]:
    with contextlib.suppress(OSError):
        with open("/proc/cpuinfo") as info:
            first = info.read().split("\n\n")[0]   # the first processor's entry
        fields = [line for line in first.splitlines() if line.split(":")[0].strip().lower() in CPU_FIELDS]
        if fields:
            return ("-march=native",), "\n".join(" ".join(line.split()) for line in fields)
    try:
        out = subprocess.run([cc, "-march=native", "-Q", "--help=target"], capture_output=True, text=True,
                             timeout=60, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return (), "default"
    # the option table, one "-mfoo  [enabled]" or "-march=  skylake" per line (headers dropped)
    lines = sorted(" ".join(line.split()) for line in out.splitlines() if line.strip().startswith("-m"))
    return (("-march=native",), "\n".join(lines)) if lines else ((), "default")


_keys: "OrderedDict[int, tuple[ca.Function, str]]" = OrderedDict()
# the serialised graph of a Function whose library is not loaded yet, from `function_key` to the
# background build that generates its source apart (`_generate_apart`); dropped once it is found
_texts: "OrderedDict[str, str]" = OrderedDict()
MAX_TEXTS = 32
# C sources this process has written already (the quick tier's, solvers/dynamics/quick.py: the same
# file gcc's build would write, its driver appended), by function key: a background build takes
# one instead of generating it again in a child interpreter (a Python process importing CasADi,
# ~0.2 s of CPU per library)
_sources: "OrderedDict[str, Path]" = OrderedDict()


def function_key(fn: ca.Function) -> str:
    """Hash of the Function's graph; remembered per Function object (serialising costs ~ms).

    The hash covers the serialised graph, the CasADi version, the compiler flags with the target
    instruction set (`target`) and the columns driver, so a change to any of them builds a new
    library, and a cache shared by different CPUs holds one library per CPU.

    Parameters
    ----------
    fn : casadi.Function
        The Function to identify.

    Returns
    -------
    str
        The first 24 hex digits of the SHA-256 of that text.
    """
    known = _keys.get(id(fn))
    if known is not None and known[0] is fn:
        return known[1]
    flags, isa = target()
    serialised = fn.serialize()
    text = serialised + ca.__version__ + " ".join((*CFLAGS, *flags, "-O3/-O1")) + isa + COLUMNS_DRIVER
    key = hashlib.sha256(text.encode()).hexdigest()[:24]
    _keys[id(fn)] = (fn, key)   # holding fn keeps its id from being reused
    while len(_keys) > 256:
        _keys.popitem(last=False)
    with _lock:
        _texts[key] = serialised
        while len(_texts) > MAX_TEXTS:
            _texts.popitem(last=False)
    return key


def offer_source(key: str, source: Path) -> None:
    """Offer the C source of the Function with this key (`function_key`), its driver appended, to
    this process's gcc build of it: the build copies it rather than generating it again.

    Parameters
    ----------
    key : str
        The Function's key.
    source : pathlib.Path
        The source file; the build deletes it once copied.
    """
    with _lock:
        _sources[key] = source
        while len(_sources) > MAX_TEXTS:
            _sources.popitem(last=False)


def _take_source(key: str, into: Path) -> bool:
    """Copy an offered source to `into` (and delete the offered file); False where none is."""
    with _lock:
        given = _sources.pop(key, None)
    if given is None:
        return False
    try:
        shutil.copyfile(given, into)
    except OSError:
        return False
    given.unlink(missing_ok=True)
    return True


def loaded(fn: ca.Function) -> ca.Function | None:
    """The compiled Function of `fn` if this process has loaded it already (no policy weighing).

    Parameters
    ----------
    fn : casadi.Function
        The interpreted Function.

    Returns
    -------
    casadi.Function or None
        The loaded external Function (now marked most recently used), or None when it is not loaded,
        the mode is ``never`` or there is no compiler.
    """
    if mode() == "never" or compiler() is None:
        return None
    key = function_key(fn)
    with _lock:
        ext = _memory.pop(key, None)
        if ext is not None:
            _memory[key] = ext   # the most recently used now
            _texts.pop(key, None)
        return ext


def max_loaded() -> int:
    """How many compiled model structures a process keeps loaded (`GREYFIT_COMPILED_IN_MEMORY`).

    Returns
    -------
    int
        The setting (at least 1), else MAX_LOADED.
    """
    value = os.environ.get("GREYFIT_COMPILED_IN_MEMORY", "")
    return max(1, int(value)) if value.strip().isdigit() else MAX_LOADED


def _cache_max_bytes() -> int:
    value = os.environ.get("GREYFIT_CACHE_MAX_BYTES", "")
    return int(value) if value.strip().isdigit() else DEFAULT_CACHE_MAX_BYTES


def compiled(fn: ca.Function, evaluations: float = 0.0,
             interpret_meanwhile: bool = False) -> tuple[ca.Function, bool]:
    """(Function to use, whether it is compiled C) for `fn`, evaluated about `evaluations` times.

    Never raises for a missing compiler or a failed compile: the interpreted `fn` is returned.

    Parameters
    ----------
    fn : casadi.Function
        The interpreted Function.
    evaluations : float, optional
        Expected number of evaluations; with the graph's size it decides whether compiling in the
        foreground repays the compile (see `library`).
    interpret_meanwhile : bool, optional
        The caller switches to the compiled Function once its build has ended: in ``auto``
        mode a missing library is then always built in the background (see `library`).

    Returns
    -------
    function : casadi.Function
        The compiled external Function, or `fn` itself.
    is_compiled : bool
        Whether `function` is compiled C.
    """
    ready = loaded(fn)
    if ready is not None:
        return ready, True
    path = library(fn, evaluations, interpret_meanwhile)
    if path is None:
        return fn, False
    return _load(fn, function_key(fn), path), True


def built(fn: ca.Function) -> Path | None:
    """The library of `fn` if it is on disk already (nothing is built or started).

    Parameters
    ----------
    fn : casadi.Function
        The interpreted Function.

    Returns
    -------
    pathlib.Path or None
        Its path, or None where it is missing, the mode is ``never`` or there is no compiler.
    """
    if mode() == "never" or compiler() is None:
        return None
    path = _library_path(fn, function_key(fn))
    return path if path.exists() else None


def _library_path(fn: ca.Function, key: str) -> Path:
    return cache_dir() / f"{fn.name()}_{key}.so"


def library(fn: ca.Function, evaluations: float = 0.0, interpret_meanwhile: bool = False) -> Path | None:
    """The compiled library of `fn` (built now, found on disk, or None while it is built in the
    background / where nothing can be compiled), under the policy of `GREYFIT_COMPILE`.

    In ``auto`` mode, the library is built now when interpreting `fn` `evaluations` times is
    expected to take longer than about a second and than gcc (`foreground_pays`); otherwise a
    background build is started (unless one is running or a failed one is still backing off) and
    None is returned.

    Parameters
    ----------
    fn : casadi.Function
        The interpreted Function.
    evaluations : float, optional
        Expected number of evaluations of `fn`.
    interpret_meanwhile : bool, optional
        Never build in the foreground in ``auto`` mode: the caller interprets meanwhile.

    Returns
    -------
    pathlib.Path or None
        Path of the shared library, or None as described above (also when a foreground build fails).
    """
    how = mode()
    if how == "never" or compiler() is None:
        return None
    key = function_key(fn)
    path = _library_path(fn, key)
    if path.exists():
        with _lock:
            _texts.pop(key, None)
        return path
    if how == "always" or (not interpret_meanwhile and foreground_pays(fn.n_instructions(), evaluations)):
        with _lock:
            _texts.pop(key, None)
        return path if _build(fn, path) else None
    with _lock:
        failed = _failed.get(key)
        start = key not in _pending and (failed is None or time.monotonic() >= failed[1])
        serialised = _texts.pop(key, None)
        work = fn.n_instructions() * max(float(evaluations), 1.0) if start else 0.0
        if start:
            _pending.add(key)
            _building[key] = (fn, path, work)
    if start:   # the next fit of this model structure will find it
        threading.Thread(target=_build_in_background, args=(fn, path, key, work, serialised), daemon=True).start()
    return None


def foreground_pays(instructions: float, evaluations: float) -> bool:
    """Whether a fit about to evaluate a Function that often should wait for gcc rather than interpret
    it while gcc runs in the background: the interpreted work must reach `FOREGROUND_WORK` and take
    longer than gcc is expected to.

    Parameters
    ----------
    instructions : float
        The Function's instructions (`casadi.Function.n_instructions`).
    evaluations : float
        Expected evaluations of it in the fit.

    Returns
    -------
    bool
        True when compiling first is expected to end the fit sooner.
    """
    work = instructions * evaluations
    return work >= FOREGROUND_WORK and \
        work * INTERPRET_S_PER_INSTRUCTION > COMPILE_S + COMPILE_S_PER_INSTRUCTION * instructions


def building_any() -> bool:
    """Whether a background build runs in this process.

    Returns
    -------
    bool
        True while at least one library is being built here.
    """
    with _lock:
        return bool(_pending)


def builds_ended() -> int:
    """How many background builds of this process have ended (built, failed or given up): a loop
    running a stand-in (the interpreter, or the quick tier's library) asks for gcc's library again
    only when this has moved, not at every call.

    Returns
    -------
    int
        A count that only grows.
    """
    return _ended[0]


def wait_for_builds(timeout: float) -> bool:
    """Wait until the background builds of this process have ended (or `timeout` has passed).

    Parameters
    ----------
    timeout : float
        Longest wait, in seconds.

    Returns
    -------
    bool
        True when none is running any more.
    """
    deadline = time.monotonic() + timeout
    while True:
        with _lock:
            if not _pending:
                return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.05)


def abandon_builds(timeout: float) -> list[tuple[ca.Function, Path, float]]:
    """Stop this process's background builds: those waiting for a compile slot or a lock give up,
    running compilers are killed, none starts; each build's thread then removes its temporary
    folder. For a process about to exit (the CLI, once its answer is printed).

    Parameters
    ----------
    timeout : float
        Longest wait, in seconds, for the builds' threads to end (the C source of a Function
        generated in this process cannot be stopped: it takes ~0.1 s).

    Returns
    -------
    list of (casadi.Function, pathlib.Path, float)
        The Function, library path and expected work of each build whose library is not on disk.
    """
    with _lock:
        builds = list(_building.values())
    _abandon.set()
    with _turn:
        _turn.notify_all()
    _end_children()
    wait_for_builds(timeout)
    return [build for build in builds if not build[1].exists()]


def _build_in_background(fn: ca.Function, path: Path, key: str, work: float = 0.0,
                         serialised: str | None = None) -> None:
    ok: bool | None = False
    try:
        ok = _build(fn, path, queue=True, work=work, serialised=serialised)
    finally:   # whatever happened, the key is no longer pending (else it would never be built again)
        _settle(key, ok)


def _settle(key: str, ok: bool | None) -> None:
    """`ok` None: the build never had its turn at the compiler (not a failure: asked again next time)."""
    with _lock:
        _pending.discard(key)
        _building.pop(key, None)
        _ended[0] += 1
        if ok is None:
            return
        if ok:
            _failed.pop(key, None)
        else:
            failures = _failed.get(key, (0, 0.0))[0] + 1
            wait = min(RETRY_AFTER_S * 2 ** (failures - 1), MAX_RETRY_S)
            _failed[key] = (failures, time.monotonic() + wait)


def _load(fn: ca.Function, key: str, library: Path) -> ca.Function:
    # derivatives come as outputs of the compiled Functions themselves; finite differences only
    # let CasADi build (never evaluate) the derivative functions an NLP interface asks for
    ext = ca.external(fn.name(), str(library), {"enable_fd": True})
    with _lock:
        _memory[key] = ext
        while len(_memory) > max_loaded():
            del _memory[next(iter(_memory))]   # the least recently used
    return ext


def prune_disk_cache(folder: Path, keep: Path | None = None) -> int:
    """Delete the oldest libraries of `folder` until it holds at most `GREYFIT_CACHE_MAX_BYTES`,
    sparing `keep` and any built in the last KEEP_RECENT_S. Returns how many were deleted.

    Parameters
    ----------
    folder : pathlib.Path
        The cache folder holding the ``*.so`` libraries.
    keep : pathlib.Path or None, optional
        A library never to delete (the one just built).

    Returns
    -------
    int
        Number of libraries deleted (0 when the folder cannot be listed).
    """
    try:
        entries = [(p.stat().st_mtime, p.stat().st_size, p) for p in folder.glob("*.so")]
    except OSError:
        return 0
    total, limit, now, deleted = sum(size for _, size, _ in entries), _cache_max_bytes(), time.time(), 0
    for mtime, size, path in sorted(entries, key=lambda e: e[0]):
        if total <= limit:
            break
        if path == keep or now - mtime < KEEP_RECENT_S:
            continue
        with contextlib.suppress(OSError):
            path.unlink()
            path.with_suffix(".lock").unlink(missing_ok=True)
            total -= size
            deleted += 1
    return deleted


def _build(fn: ca.Function, library: Path, queue: bool = False, work: float = 0.0,
           serialised: str | None = None) -> bool | None:
    """Build `library` from `fn`; `queue`: wait for one of the compile slots first (a background
    build: the fit goes on interpreted meanwhile; `work`, its expected instructions evaluated, puts
    it ahead of this process's smaller builds; None when no slot came within `SLOT_WAIT_S`: nothing
    was compiled), then generate the source from `serialised` (`fn.serialize()`) in a child
    interpreter where it is given. A foreground build never waits for a slot: a fit is waiting for
    it, and the number of fits running bounds the number of such builds."""
    try:
        library.parent.mkdir(parents=True, exist_ok=True)
        with _build_lock(library):
            if library.exists():   # another process built it while this one waited
                return True
            with tempfile.TemporaryDirectory(dir=library.parent) as tmp:
                source = Path(tmp) / f"{fn.name()}.c"
                lib = Path(tmp) / "lib.so"
                with _compile_slot(library.parent, work) if queue else contextlib.nullcontext(True) as turn:
                    if not turn:
                        return None
                    if not _take_source(function_key(fn), source):
                        if not (queue and serialised is not None and _generate_apart(serialised, source)):
                            gen = ca.CodeGenerator(source.name, {"with_header": False})
                            gen.add(fn)
                            gen.generate(tmp + os.sep)
                        with open(source, "a") as c_file:   # columns.py's loop over samples
                            c_file.write(COLUMNS_DRIVER.replace("FN", fn.name()))
                    flags = optimisation_flags(source.stat().st_size)
                    if flags is None:
                        return False
                    if not _run_compiler([_compiler_path(), *flags, *CFLAGS, *target()[0], str(source),
                                          "-o", str(lib), "-lm"]):
                        return False
                os.replace(lib, library)   # atomic: other processes see all of it or nothing
        prune_disk_cache(library.parent, keep=library)
        return True
    except (OSError, subprocess.SubprocessError, RuntimeError):
        return False


# deserialise, generate C: in a child, as this process would (the same CasADi writes the same file)
_GENERATE = ("import sys, casadi as ca; f = ca.Function.deserialize(sys.stdin.read()); "
             "g = ca.CodeGenerator(sys.argv[1], {'with_header': False}); g.add(f); g.generate(sys.argv[2])")


def _generate_apart(serialised: str, source: Path) -> bool:
    """Write the C source of a serialised Function to `source` from a child interpreter: CasADi
    holds the GIL while it generates, and a new model structure's background builds generating in
    this process took 0.14 s from the seat model's first fit (1.3 s), which waited on them.

    Parameters
    ----------
    serialised : str
        The Function, `casadi.Function.serialize()`.
    source : pathlib.Path
        Where the source goes (its name is the generated file's).

    Returns
    -------
    bool
        Whether the source was written (False: generate in this process instead).
    """
    try:
        with _child([sys.executable, "-c", _GENERATE, source.name, str(source.parent) + os.sep],
                    stdin=subprocess.PIPE) as proc:
            proc.communicate(serialised, timeout=COMPILE_TIMEOUT_S)
    except (OSError, subprocess.SubprocessError):
        return False
    return proc.returncode == 0 and source.exists()


def optimisation_flags(source_bytes: int) -> list[str] | None:
    """The optimisation level for a generated source of this size; None: too large to compile.

    gcc's time and memory at -O3 grow faster than linearly on CasADi's straight-line code: a 3 MB
    source (a sensitivity kernel of a discovery candidate) ran past the 120 s limit at -O3 with 3 GB
    of memory, a 12 MB one never ended. -O1 compiles those in a fraction, and the numbers do not
    depend on the level (no fused or reassociated arithmetic at any level: -ffp-contract=off).

    Parameters
    ----------
    source_bytes : int
        Size of the generated C source.

    Returns
    -------
    list of str or None
        ``["-O3"]``, ``["-O1"]`` above `LARGE_SOURCE_BYTES`, None above `MAX_SOURCE_BYTES`.
    """
    if source_bytes > MAX_SOURCE_BYTES:
        return None
    return ["-O1"] if source_bytes > LARGE_SOURCE_BYTES else ["-O3"]


def _run_compiler(command: list[str]) -> bool:
    """Run gcc with a time limit that ends all of it.

    gcc's driver runs `cc1` and `as` as children of its own: killing only the driver on a timeout
    (what `subprocess.run(timeout=...)` does) left `cc1` running, orphaned, for as long as it took
    (seen: a dozen of them, 3 GB each, for half an hour). So the compiler runs in a session of its
    own under coreutils' `timeout`, which signals the whole group even if this process dies, and a
    timeout here kills the group too.
    """
    guard = shutil.which("timeout")
    if guard is not None:
        command = [guard, "-s", "KILL", str(COMPILE_TIMEOUT_S), *command]
    try:
        with _child(command) as proc:
            return proc.wait(timeout=COMPILE_TIMEOUT_S + 5) == 0
    except subprocess.TimeoutExpired:   # `_child` has ended the group
        return False


@contextlib.contextmanager
def _child(command: list[str], stdin: int | None = None) -> Iterator[subprocess.Popen]:
    """`command` in a session of its own, registered while it runs; its whole group is killed when
    the block raises (a time limit) and when this process exits first (`_end_children`); none
    starts once the builds are abandoned (`abandon_builds`)."""
    if _abandon.is_set():
        raise OSError("the background builds were abandoned")
    proc = subprocess.Popen(command, stdin=stdin, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            text=stdin is not None, start_new_session=True)
    with _lock:
        _children.add(proc)
    try:
        yield proc
    except subprocess.TimeoutExpired:
        _kill_group(proc)
        proc.wait()
        raise
    finally:
        with _lock:
            _children.discard(proc)


def _kill_group(proc: subprocess.Popen) -> None:
    with contextlib.suppress(OSError):
        os.killpg(proc.pid, signal.SIGKILL)


@atexit.register
def _end_children() -> None:
    """A process that exits while it builds in the background (a script whose fit has returned) takes
    its compilers with it: their output would go to a temporary folder removed at exit, and left
    running they took a core from the next process's first fit (the seat model's 0.46 s became
    0.65-0.74 s). The CLI waits for its builds instead (`service.cli`)."""
    with _lock:
        running = list(_children)
    for proc in running:
        _kill_group(proc)


def compile_slots() -> int:
    """How many compilers may run at once on this machine, across processes (`GREYFIT_COMPILE_SLOTS`).

    Returns
    -------
    int
        The setting, else half the CPUs (at least one): compiles are background work beside fits;
        a value that is not a whole number of at least 1 gives the default, with a `RuntimeWarning`
        the first time.
    """
    value = os.environ.get("GREYFIT_COMPILE_SLOTS", "").strip()
    default = max(1, (os.cpu_count() or 2) // 2)
    if value.isdigit() and int(value) > 0:
        return int(value)
    if value:   # a typo would otherwise go unseen
        _unknown_setting("GREYFIT_COMPILE_SLOTS", value, ("a whole number of at least 1",), str(default))
    return default


# This process's background builds waiting for a compile slot, largest expected work first: a new
# model structure starts a dozen at once, and in the order they happened to poll, the two kernels
# every later single-shooting fit of the seat model runs were built 7th and 12th of 13 (7 and 12 s
# after its first fit began), behind the checks' kernels
_waiting: list[tuple[float, int]] = []
_turn = threading.Condition()
_tickets = itertools.count()


@contextlib.contextmanager
def _compile_slot(folder: Path, work: float = 0.0) -> Iterator[bool]:
    """One of `compile_slots()` lock files in `folder`, held while gcc runs: worker processes that meet
    many new model structures at once (a discovery's refits, a batch of new models) queue for the
    compiler instead of starting one each; within a process the build with the most `work` goes
    first. Yields whether the slot came within `SLOT_WAIT_S`: a build that waited longer compiles
    nothing (it used to go on without a slot, and a discovery's few hundred queued builds then all
    ran gcc at once after two minutes: 50 compilers, a load average of 200 on 2 cores)."""
    if fcntl is None:
        yield True
        return
    handles = [open(folder / f".compile-slot-{i}", "a") for i in range(compile_slots())]
    held = None
    ticket = (-float(work), next(_tickets))
    with _turn:
        heapq.heappush(_waiting, ticket)
    try:
        deadline = time.monotonic() + SLOT_WAIT_S
        while held is None and time.monotonic() < deadline and not _abandon.is_set():
            with _turn:
                first = _waiting[0] == ticket
            if first:
                for handle in handles:
                    try:
                        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                        held = handle
                        break
                    except BlockingIOError:
                        continue
            if held is None:
                with _turn:
                    _turn.wait(0.05)
        _leave(ticket)   # the next in line may take another slot now
        yield held is not None
    finally:
        if held is not None:
            fcntl.flock(held, fcntl.LOCK_UN)
        for handle in handles:
            handle.close()
        _leave(ticket)   # (again, after a failure before the slot) and wake the next


def _leave(ticket: tuple[float, int]) -> None:
    with _turn:
        if ticket in _waiting:
            _waiting.remove(ticket)
            heapq.heapify(_waiting)
        _turn.notify_all()


@contextlib.contextmanager
def _build_lock(library: Path):
    """Exclusive across processes while `library` is built. The kernel drops a flock when its holder
    dies, so a killed build never leaves the others waiting; a holder that outlives a compile's
    timeout is not waited for any longer (the waiter then builds too, as without the lock)."""
    if fcntl is None:
        yield
        return
    with open(library.with_suffix(".lock"), "a") as handle:
        deadline = time.monotonic() + COMPILE_TIMEOUT_S + 10
        while True:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if _abandon.is_set():   # the process is leaving: this build is handed over
                    raise OSError("abandoned") from None
                if time.monotonic() > deadline:
                    break
                time.sleep(0.02)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)
