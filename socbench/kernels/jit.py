"""How socbench compiles: numba, lazily, cached on disk under a fingerprint of the compiled sources.

* :func:`available` tells whether numba can be imported (without importing it: cheap, used by ``engine="auto"``);
* :func:`kernel` is the one decorator every compiled function uses: ``numba.njit`` with ``cache=True`` (the compile
  is paid once per machine), ``error_model="numpy"`` (a division by zero gives inf/NaN as in numpy instead of raising)
  and no fast-math (IEEE arithmetic, NaN propagation: the compiled path must equal the numpy path to 1e-9).

Nothing compiles at import time: numba compiles a function on its first call. The kernel modules themselves are only
imported when a compiled engine is used (``socbench.estimators`` and ``socbench.identify`` import them lazily), so
``import socbench`` does not import numba.

**Cache.** numba keys a cached function on the file it is defined in, not on the files of the functions it calls, so
editing a shared helper would leave stale machine code behind. Here every compiled function shares one cache
directory named after a SHA-256 of *all* the compiled sources (the files listed in :data:`SOURCES`) and the numba
version: any edit to any of them starts a fresh cache. The directory is
``$SOCBENCH_NUMBA_CACHE`` if set, else ``$NUMBA_CACHE_DIR/socbench`` if that is set, else
``~/.cache/socbench/numba`` (``$XDG_CACHE_HOME`` respected), followed by the fingerprint. Inside it a function is
found by its file's path within the package and stamped with the fingerprint (:func:`_locator_class`), not by the
file's absolute path and modification time as numba's own locators do: a fresh checkout, a reinstall or a copy of the
same sources loads what was compiled before.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import time
from functools import cache
from pathlib import Path

#: every file holding compiled code or constants compiled into it (relative to the socbench package): their bytes
#: name the cache directory
SOURCES = (
    "kernels/jit.py",
    "kernels/lowering.py",
    "kernels/evaluate.py",
    "kernels/linalg.py",
    "kernels/filters.py",
    "kernels/pf.py",
    "kernels/openloop.py",
    "estimators/draws.py",
    "estimators/safety.py",
    "models/blocks.py",
    "models/effects.py",
    "ocv.py",
)


@cache
def available() -> bool:
    """Whether numba is importable (checked without importing it)."""
    if os.environ.get("SOCBENCH_DISABLE_NUMBA"):
        return False
    return importlib.util.find_spec("numba") is not None


#: the socbench package folder: :data:`SOURCES` and the cache's per-file folders are named relative to it
PACKAGE = Path(__file__).resolve().parents[1]


@cache
def fingerprint() -> str:
    """SHA-256 (16 hex digits) of the compiled sources and the numba version."""
    import numba

    h = hashlib.sha256(numba.__version__.encode())
    for rel in SOURCES:
        path = PACKAGE / rel
        h.update(rel.encode())
        h.update(path.read_bytes() if path.exists() else b"")
    return h.hexdigest()[:16]


def cache_dir() -> Path:
    """Where the compiled kernels are cached (see the module docstring)."""
    if os.environ.get("SOCBENCH_NUMBA_CACHE"):
        base = Path(os.environ["SOCBENCH_NUMBA_CACHE"])
    elif os.environ.get("NUMBA_CACHE_DIR"):
        base = Path(os.environ["NUMBA_CACHE_DIR"]) / "socbench"
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "socbench" / "numba"
    return base / fingerprint()


@cache
def _locator_class():
    """numba's cache locator for socbench's compiled functions (see :func:`_configured`)."""
    from numba.core.caching import _CacheLocator

    class FingerprintLocator(_CacheLocator):
        """A function of a socbench source file is cached in :func:`cache_dir` (named by the fingerprint of every
        compiled source), in a folder per source file named by its path inside the package, and stamped with the
        fingerprint. numba's own locators key a cache on the file's absolute path and stamp it with its modification
        time: a fresh checkout or a reinstall of the very same sources compiled every kernel again (minutes)."""

        def __init__(self, py_func, relative: str):
            self._lineno = py_func.__code__.co_firstlineno
            self._path = str(cache_dir() / relative.replace("/", "_").removesuffix(".py"))

        def get_cache_path(self):
            return self._path

        def get_source_stamp(self):
            return fingerprint()

        def get_disambiguator(self):
            return str(self._lineno)

        @classmethod
        def from_function(cls, py_func, py_file):
            try:
                relative = Path(py_file).resolve().relative_to(PACKAGE).as_posix()
            except (OSError, ValueError):  # not a socbench file: numba's own locators take it
                return None
            locator = cls(py_func, relative)
            try:
                locator.ensure_cache_path()
            except OSError:
                return None
            return locator

    return FingerprintLocator


@cache
def _configured() -> bool:
    """Point numba's cache for socbench's functions at :func:`cache_dir`: by :func:`_locator_class`, first among
    numba's locators (it takes socbench's files only), or, with a numba that has no such hook, by
    ``numba.config.CACHE_DIR`` (keyed on path and modification time again)."""
    import numba

    path = cache_dir()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:  # a read-only home: numba falls back to its own locations
        return False
    try:
        from numba.core.caching import CacheImpl

        locators = CacheImpl._locator_classes
        locator = _locator_class()
    except (ImportError, AttributeError):
        numba.config.CACHE_DIR = str(path)  # read when a dispatcher enables caching, i.e. at decoration below
        return True
    if locator not in locators:
        locators.insert(0, locator)
    return True


def kernel(fn=None, *, inline: bool = False):
    """``numba.njit(cache=True, error_model="numpy", nogil=True)``: see the module docstring.

    ``inline=True`` for a small helper with few call sites: numba inlines its body into each caller (at its IR level)
    instead of calling it. A numba call that LLVM does not inline costs tens of nanoseconds (every array argument is
    passed as a struct of 7–9 words, and reference-counted), which is the whole cost of a one-line helper; inlining
    everything, on the other hand, multiplies the code to compile, so only leaves are inlined.
    """
    import numba

    _configured()

    def wrap(f):
        if inline:
            return numba.njit(cache=True, error_model="numpy", nogil=True, inline="always")(f)
        return numba.njit(cache=True, error_model="numpy", nogil=True)(f)

    return wrap(fn) if fn is not None else wrap


#: seconds spent in the first call of each entry point in this process (compile or cache load included)
FIRST_CALL_S: dict = {}


def timed_first_call(name: str, fn, *args):
    """``fn(*args)``, recording the duration of the first call of ``name`` in :data:`FIRST_CALL_S`."""
    if name in FIRST_CALL_S:
        return fn(*args)
    t0 = time.perf_counter()
    out = fn(*args)
    FIRST_CALL_S[name] = time.perf_counter() - t0
    return out
