"""lightplane's numba kernels: one decorator, one cache folder, one notice when they compile.

Every kernel of the package is declared with :func:`njit_cached` (``numba.njit`` with lightplane's
own on-disk cache).  numba compiles a kernel for this machine the first time it runs with a new
type of argument; the machine code is kept in a per-user folder, so that later processes load it
in milliseconds:

- the folder: ``$LIGHTPLANE_CACHE_DIR`` if set, else the user's cache folder
  (``$XDG_CACHE_HOME/lightplane`` or ``~/.cache/lightplane`` on Linux, ``~/Library/Caches/lightplane``
  on macOS, ``%LOCALAPPDATA%\\lightplane\\cache`` on Windows); the kernels under
  ``numba/<lightplane version>/<package>/`` (:func:`kernel_cache_dir`), read when lightplane is imported;
- an entry is valid for lightplane's version and the *content* of the kernel's source file (and of
  the lightplane modules that file imports, whose functions it may compile in), not the file's
  time stamp: reinstalling the same version, or installing it into a read-only ``site-packages``,
  keeps the compiled kernels; numba's version, Python's and the CPU are part of numba's own key;
- only lightplane's kernels use this folder (a numba cache locator given to each of them): nothing
  process-wide is set, ``NUMBA_CACHE_DIR`` and other numba functions are left alone.  Where the
  folder cannot be written the kernels fall back to numba's own cache places, else to no cache.

Compilation is announced: :func:`set_compile_listener` registers a function called once per
process, right before the first kernel that is not in the cache is compiled (the command line
prints one line with it, :func:`compile_notice`).  Finding out costs nothing: it is the cache's
own miss.  :func:`compile_seconds` is the time spent compiling so far in this process.
"""

from __future__ import annotations

import functools
import hashlib
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numba
from numba.core import caching

from lightplane.version import __version__

__all__ = ["njit_cached", "cache_root", "kernel_cache_dir", "cached_kernels", "set_compile_listener",
           "notify_compiling", "is_cold", "compile_notice", "compile_seconds", "compiled_count", "index_files", "record_compile_seconds",
           "CACHE_ENV", "DEFAULT_COMPILE_ESTIMATE_S"]

#: the environment variable that moves lightplane's cache folder
CACHE_ENV = "LIGHTPLANE_CACHE_DIR"
#: the notice's estimate before any compilation has been timed on this machine, s (the measure
#: path's kernels took ~25 s of CPU time on a 2-core machine: benchmarks/bench_first_run.py)
DEFAULT_COMPILE_ESTIMATE_S = 30.0
_ESTIMATE_FILE = "compile-seconds.txt"


def _user_cache_dir() -> Path:
    """The platform's per-user cache folder (what ``platformdirs.user_cache_dir`` gives)."""
    if sys.platform.startswith("win"):
        base = os.environ.get("LOCALAPPDATA") or str(Path.home() / "AppData" / "Local")
        return Path(base) / "lightplane" / "cache"
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches" / "lightplane"
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    return (Path(xdg) if os.path.isabs(xdg) else Path.home() / ".cache") / "lightplane"


def cache_root() -> Path:
    """lightplane's cache folder: ``$LIGHTPLANE_CACHE_DIR``, else the user's cache folder's ``lightplane``."""
    env = os.environ.get(CACHE_ENV, "")
    return Path(env).expanduser() if env else _user_cache_dir()


def kernel_cache_dir() -> Path:
    """Where this version's compiled kernels are kept: ``cache_root()/numba/<version>``."""
    return cache_root() / "numba" / __version__


# ----------------------------------------------------------------------------- the cache
@functools.lru_cache(maxsize=None)
def _file_digest(path: str) -> str:
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


def _source_files(py_func) -> list[str]:
    """The kernel's source file and those of the lightplane modules its module imports."""
    files = {os.path.abspath(py_func.__code__.co_filename)}
    module = sys.modules.get(py_func.__module__)
    for value in vars(module).values() if module is not None else ():
        name = getattr(value, "__module__", None) if not isinstance(value, type(sys)) else value.__name__
        mod = sys.modules.get(name) if isinstance(name, str) and name.startswith("lightplane.") else None
        path = getattr(mod, "__file__", None)
        if path and path.endswith(".py"):
            files.add(os.path.abspath(path))
    return sorted(files)


_checked_dirs: set[str] = set()
_building = threading.local()   # the options tag of the kernel whose cache is being made


class _KernelLocator(caching._CacheLocator):
    """lightplane's place for a kernel's cache files (see the module's notes)."""

    def __init__(self, py_func, py_file):
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        self._tag = getattr(_building, "tag", "")
        package = py_func.__module__.split(".")[1:-1] or ["lightplane"]
        self._cache_path = str(kernel_cache_dir().joinpath(*package))
        self._stamp = (__version__, tuple(_file_digest(p) for p in _source_files(py_func)))

    def ensure_cache_path(self):
        if self._cache_path not in _checked_dirs:   # once per folder (import time: one check, not one a kernel)
            super().ensure_cache_path()
            _checked_dirs.add(self._cache_path)

    def get_cache_path(self):
        return self._cache_path

    def get_source_stamp(self):
        return self._stamp

    def get_disambiguator(self):
        return f"{self._lineno}{self._tag}"

    @classmethod
    def from_function(cls, py_func, py_file):
        if not os.path.isfile(py_file):
            return None
        try:
            self = cls(py_func, py_file)
            self.ensure_cache_path()
        except OSError:   # the folder cannot be made or written: numba's own places
            return None
        return self


class _KernelCacheImpl(caching.CompileResultCacheImpl):
    _locator_classes = [_KernelLocator, *caching.CompileResultCacheImpl._locator_classes]


_lock = threading.RLock()
_state: dict[str, Any] = {"listener": None, "told": False, "compiled": 0, "depth": 0, "t0": 0.0, "seconds": 0.0}


class _KernelCache(caching.FunctionCache):
    """numba's function cache in lightplane's folder; a miss (a compilation to come) is announced."""

    _impl_class = _KernelCacheImpl

    def load_overload(self, sig, target_context):
        data = super().load_overload(sig, target_context)
        if data is None:
            _compiling()
        return data

    def save_overload(self, sig, data):
        _compiled()
        super().save_overload(sig, data)


def _compiling() -> None:
    """A kernel is about to be compiled: tell the listener (once), start the clock."""
    with _lock:
        if _state["depth"] == 0:
            _state["t0"] = time.perf_counter()
        _state["depth"] += 1
        listener, told = _state["listener"], _state["told"]
        _state["told"] = True
    if listener is not None and not told:
        listener()


def _compiled() -> None:
    with _lock:
        _state["compiled"] += 1
        _state["depth"] = max(0, _state["depth"] - 1)
        if _state["depth"] == 0:
            _state["seconds"] += time.perf_counter() - _state["t0"]


_KERNELS: list = []


def njit_cached(func: Callable | None = None, /, **options: Any):
    """``numba.njit(**options)`` with lightplane's on-disk cache (``cache=True`` is implied).

    Use as ``@njit_cached`` or ``@njit_cached(parallel=True, ...)`` or
    ``njit_cached(inline="always")(py_func)``."""
    options.pop("cache", None)
    tag = "" if not options else "-" + hashlib.sha1(repr(sorted(options.items())).encode()).hexdigest()[:6]

    def wrap(py_func):
        disp = numba.njit(**options)(py_func)
        _building.tag = tag
        try:
            disp._cache = _KernelCache(py_func)
        except RuntimeError:   # no writable place at all: numba's own cache, else none
            try:
                disp.enable_caching()
            except RuntimeError:
                pass
        finally:
            _building.tag = ""
        _KERNELS.append(disp)
        return disp

    return wrap(func) if func is not None else wrap


def cached_kernels() -> list:
    """Every kernel declared with :func:`njit_cached` so far (their numba dispatchers)."""
    return list(_KERNELS)


def index_files(kernel) -> list[Path]:
    """A kernel's cache index file where it exists (empty list: the kernel was never compiled and
    saved here); a check of the folder only, it compiles nothing."""
    cache = getattr(kernel, "_cache", None)
    path = getattr(getattr(cache, "_cache_file", None), "_index_path", None)
    return [Path(path)] if path and os.path.exists(path) else []


# ----------------------------------------------------------------------------- the notice
def set_compile_listener(listener: Callable[[], None] | None) -> None:
    """``listener()`` is called once in this process, right before lightplane first compiles a
    kernel that is not in its cache (None: no listener).  Setting one resets the once."""
    with _lock:
        _state["listener"] = listener
        _state["told"] = False


def notify_compiling() -> None:
    """Tell the listener now (once a process, as a cache miss would): for work about to compile
    kernels elsewhere, e.g. in worker processes started by this one, which have no listener."""
    with _lock:
        listener, told = _state["listener"], _state["told"]
        _state["told"] = True
    if listener is not None and not told:
        listener()


def is_cold(kernels) -> bool:
    """Whether any of ``kernels`` has no cache index file yet (:func:`index_files`): a look at the
    folder, nothing is compiled.  (An index file may still lack the argument types a run needs:
    then the miss itself gives the notice.)"""
    return any(not index_files(k) for k in kernels)


def compiled_count() -> int:
    """How many kernel specialisations this process has compiled (not loaded from the cache)."""
    return int(_state["compiled"])


def compile_seconds() -> float:
    """Seconds this process has spent compiling kernels (wall time, nested compilations once)."""
    return float(_state["seconds"])


def _estimate_s() -> float:
    try:
        return float((kernel_cache_dir() / _ESTIMATE_FILE).read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return DEFAULT_COMPILE_ESTIMATE_S


def compile_notice() -> str:
    """The line announcing a compilation, with the last compilation's time on this machine as
    the estimate (:func:`record_compile_seconds`)."""
    est = _estimate_s()
    return (f"compiling lightplane's kernels for this machine (once per version and pixel type, "
            f"about {max(5, int(round(est / 5.0)) * 5)} s) ...")


def record_compile_seconds(minimum: float = 5.0) -> None:
    """Keep this process's compile time (when at least ``minimum`` s) as the next notice's estimate."""
    s = compile_seconds()
    if s < minimum:
        return
    try:
        (kernel_cache_dir() / _ESTIMATE_FILE).write_text(f"{s:.1f}\n")
    except OSError:
        pass
