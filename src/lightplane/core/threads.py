"""One level of parallelism at a time: numba's threading layer, its wait policy, OpenCV's threads.

A sensor PC is never idle, and threads that spin or wait for each other collapse when
other processes hold the cores.  The rules, applied by the library itself:

- **frames across threads, serial kernels inside** when there are many frames
  (``measure``'s worker threads, ``calibrate-plane``'s images, Dask workers): each
  worker thread runs inside :func:`serial_kernels` (numba kernels on the calling
  thread only, :func:`lightplane.stripe.extract.extract_profile` picks its serial kernels),
  and OpenCV's own pool is set to one thread while the pool runs
  (:func:`frames_across_threads`);
- **a parallel kernel only for a single large frame** (:func:`profile_parallel`:
  at least :data:`PARALLEL_MIN_PIXELS` pixels and :data:`PARALLEL_MIN_LINES`
  lines, outside any frame pool, and only while a core is free: :func:`idle_cpus`),
  never nested inside a pool.

BLAS: the OpenBLAS / MKL pools (numpy's, scipy's and the one OpenCV's wheel brings) are
held at **one thread** while lightplane's own calibrations and scans run (:func:`blas_limited`, a
``threadpoolctl`` context around each of them; the command line holds it for the whole command),
unless the user has set ``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS``, ``BLIS_NUM_THREADS`` or
``OMP_NUM_THREADS``.  Our matrices are small (least-squares Jacobians of a few thousand rows, 3x3
and 4x4 transforms), so BLAS threads never paid here; but OpenBLAS's threads spin for ~0.1 s
after every call it splits, and on two cores they took the cores from the frame kernels that came
next (a 200-frame ROI batch took 54 ms right after a few BLAS calls against 34 ms after a 50 ms
pause, same run, medians of 8).  Outside those calls the user's own BLAS settings stand;
:func:`limit_blas` applies the same limit to the whole process for those who want it.

Threading layer: OpenMP first (thread-safe for launches from several Python threads,
unlike ``workqueue``; TBB is rarely installed), with the *passive* wait policy
(``OMP_WAIT_POLICY=PASSIVE``, ``KMP_BLOCKTIME=0``, and for GNU OpenMP a short spin first,
``GOMP_SPINCOUNT=20000`` iterations): a thread that has finished its
share sleeps soon instead of spinning on a core another process needs.  ``import lightplane``
changes none of this: :func:`ensure_configured` sets them right before lightplane launches its
first parallel kernel (the OpenMP runtime reads them once, when numba loads it), and the command
line at its start, unless the user has set them (environment variables
``NUMBA_THREADING_LAYER``, ``OMP_WAIT_POLICY``, ``KMP_BLOCKTIME``, ``GOMP_SPINCOUNT``, which win).
:func:`threading_info` reports what is in effect (printed by the benchmarks).
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading
import time
from typing import Callable, ParamSpec, TypeVar

P = ParamSpec("P")
R = TypeVar("R")

__all__ = ["serial_kernels", "frames_across_threads", "threading_info", "limit_blas", "blas_limited", "BLAS_THREADS",
           "ensure_configured", "with_blas_limited",
           "profile_parallel", "idle_cpus", "in_serial_context", "PARALLEL_MIN_PIXELS", "PARALLEL_MIN_LINES"]

#: which OpenMP runtime was already loaded before lightplane set its wait policy (then it has no effect)
_OMP_PRELOADED = None


def _omp_runtimes_loaded() -> list[str]:
    try:
        with open("/proc/self/maps") as f:
            names = {line.rsplit("/", 1)[-1].strip() for line in f if "omp" in line}
    except OSError:  # pragma: no cover - not Linux
        return []
    return sorted(n for n in names if n.startswith(("libgomp", "libomp", "libiomp")))


#: GNU OpenMP's spin count before a waiting thread sleeps (``GOMP_SPINCOUNT``, unless set)
GOMP_SPINCOUNT = 20000


_configured = False


def ensure_configured() -> None:
    """Set OpenMP's wait policy and numba's threading layer (see the module's notes) unless the user
    has set them; once, before lightplane's first parallel kernel.  Cheap after the first call."""
    global _OMP_PRELOADED, _configured
    if _configured:
        return
    _configured = True
    _OMP_PRELOADED = _omp_runtimes_loaded()
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")   # GNU and LLVM/Intel OpenMP: sleep, do not spin
    os.environ.setdefault("KMP_BLOCKTIME", "0")           # LLVM/Intel OpenMP: the same, in ms of spinning
    # GNU OpenMP: a short spin before sleeping, so that a frame's consecutive kernels find
    # the worker awake: on a virtual machine the passive sleep alone made a single 1280x960
    # profile 0.7-1.2 ms instead of 0.5 ms (same-run A/B)
    os.environ.setdefault("GOMP_SPINCOUNT", str(GOMP_SPINCOUNT))
    try:
        import numba
    except Exception:  # pragma: no cover - numba is a dependency
        return
    if "NUMBA_THREADING_LAYER" not in os.environ and numba.config.THREADING_LAYER == "default":
        numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]


#: BLAS threads lightplane leaves in numpy's, scipy's and OpenCV's pools (:func:`limit_blas`)
BLAS_THREADS = 1
_BLAS_ENV = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS", "OMP_NUM_THREADS")
#: what :func:`limit_blas` did (reported by :func:`threading_info`)
_blas_note = [f"held at {BLAS_THREADS} inside lightplane's calibrations and scans only"]


def _blas_set_by_user() -> list[str]:
    """The BLAS thread variables the user has set (then lightplane leaves the pools alone)."""
    return [v for v in _BLAS_ENV if v in os.environ]


def limit_blas() -> None:
    """numpy's, scipy's and OpenCV's BLAS pools to :data:`BLAS_THREADS` for the rest of the process
    (an opt-in: lightplane itself limits them only around its own calls, :func:`blas_limited`), unless
    one of ``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS``, ``BLIS_NUM_THREADS``, ``OMP_NUM_THREADS``
    is set: then the user's setting stands."""
    given = _blas_set_by_user()
    if given:
        _blas_note[0] = f"left as set by {', '.join(given)}"
        return
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - a dependency
        _blas_note[0] = "not limited (threadpoolctl is not installed)"
        return
    import cv2  # noqa: F401  (OpenCV's wheel brings its own OpenBLAS: load it, so it is limited too)

    threadpool_limits(limits=BLAS_THREADS, user_api="blas")
    _blas_note[0] = f"limited to {BLAS_THREADS} by lightplane"


_blas_lock = threading.Lock()
_blas_users = 0
_blas_limiter = None


@contextlib.contextmanager
def blas_limited():
    """Hold numpy's, scipy's and OpenCV's BLAS pools at :data:`BLAS_THREADS` for a block of
    lightplane's own work (its calibrations and scans), then give the user's setting back.  The
    pools are process-wide: the first block (of any thread) sets them, the last one to end restores
    them; a block entered while another runs applies the limit again (about a millisecond).  A no-op when the user has set a BLAS thread variable."""
    global _blas_users, _blas_limiter
    if _blas_set_by_user():
        yield
        return
    from threadpoolctl import threadpool_limits

    with _blas_lock:
        if _blas_users == 0:
            _blas_limiter = threadpool_limits(limits=BLAS_THREADS, user_api="blas")
        else:   # again: a library loaded since, or a pool another caller has changed meanwhile
            threadpool_limits(limits=BLAS_THREADS, user_api="blas")
        _blas_users += 1
    try:
        yield
    finally:
        with _blas_lock:
            _blas_users -= 1
            if _blas_users == 0 and _blas_limiter is not None:
                _blas_limiter.restore_original_limits()
                _blas_limiter = None


def with_blas_limited(func: Callable[P, R]) -> Callable[P, R]:
    """Decorator: ``func`` runs inside :func:`blas_limited`."""
    @functools.wraps(func)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        with blas_limited():
            return func(*args, **kwargs)
    return wrapper


def _blas_pools() -> list[tuple[str, int]]:
    try:
        from threadpoolctl import threadpool_info
    except ImportError:  # pragma: no cover - a dependency
        return []
    return [(str(d.get("internal_api")), int(d.get("num_threads", 0))) for d in threadpool_info()
            if d.get("user_api") == "blas"]


#: a single frame is split over numba's threads only from this many pixels (lines x samples) ...
PARALLEL_MIN_PIXELS = 1 << 17
#: ... and this many lines (the per-line work is most of a profile's cost)
PARALLEL_MIN_LINES = 256

_local = threading.local()
_cv_lock = threading.Lock()
_cv_users = 0
_cv_saved = None


def in_serial_context() -> bool:
    """Whether this thread runs inside :func:`serial_kernels` (one frame per thread)."""
    return getattr(_local, "depth", 0) > 0


def _numba():
    ensure_configured()  # numba's thread calls load its OpenMP runtime
    try:
        import numba

        return numba
    except Exception:  # pragma: no cover
        return None


def enter_serial() -> None:
    """:func:`serial_kernels` for the rest of this thread's life (a pool worker's initializer)."""
    _local.depth = getattr(_local, "depth", 0) + 1
    nb = _numba()
    if nb is not None:
        nb.set_num_threads(1)  # numba's thread count is per calling thread


@contextlib.contextmanager
def serial_kernels():
    """Inside the block this thread runs every numba kernel on itself alone (restored after).

    Used where the parallelism is across frames already (one frame per thread or
    process): kernels that split a frame would nest a second level of threads.
    """
    nb = _numba()
    old = nb.get_num_threads() if nb is not None else None
    _local.depth = getattr(_local, "depth", 0) + 1
    if nb is not None:
        nb.set_num_threads(1)
    try:
        yield
    finally:   # (a generator closed on another thread leaves that thread as it was)
        _local.depth = max(0, getattr(_local, "depth", 1) - 1)
        if nb is not None:
            nb.set_num_threads(old)


@contextlib.contextmanager
def frames_across_threads():
    """While a pool of frame workers runs: OpenCV's own thread pool down to one thread.

    OpenCV's thread count is process-wide; it is restored when the last such block
    (several may run at once) ends.  The workers themselves call :func:`enter_serial`.
    """
    global _cv_users, _cv_saved
    import cv2

    with _cv_lock:
        if _cv_users == 0:
            _cv_saved = cv2.getNumThreads()
            cv2.setNumThreads(1)
        _cv_users += 1
    try:
        yield
    finally:
        with _cv_lock:
            _cv_users -= 1
            if _cv_users == 0 and _cv_saved is not None:
                cv2.setNumThreads(_cv_saved)
                _cv_saved = None


#: how long a reading of the machine's run queue (:func:`idle_cpus`) is reused, s
IDLE_REFRESH_S = 0.02
_idle_time = [-1.0]
_idle_value: list[int | None] = [None]


def _own_running_threads() -> int:
    """Threads of this process that are running or runnable now (``/proc/self/task/*/stat``)."""
    n = 0
    try:
        tids = os.listdir("/proc/self/task")
    except OSError:  # pragma: no cover - not Linux
        return 1
    for tid in tids:
        try:
            with open(f"/proc/self/task/{tid}/stat") as f:
                st = f.read()
        except OSError:   # the thread ended meanwhile
            continue
        state = st[st.rindex(")") + 2:].split(maxsplit=1)[0]   # after "pid (comm) "
        if state == "R":
            n += 1
    return max(n, 1)


def _runnable_tasks() -> int:
    """Runnable tasks of the whole machine now, the caller included (``/proc/loadavg``)."""
    with open("/proc/loadavg") as f:
        return int(f.read().split()[3].split("/")[0])


def _usable_cpus() -> int:
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1  # pragma: no cover - not Linux


def idle_cpus() -> int | None:
    """CPUs free for a second thread of this caller right now; None where unknown.

    The usable CPUs less the one the calling thread runs on, less the runnable tasks
    of *other* processes (``/proc/loadavg`` counts every runnable task; this
    process's own running threads, read from ``/proc/self/task``, are taken out, so
    that numba's workers falling asleep after the previous kernel do not make the
    next frame look like it has a busy machine).  Re-read every :data:`IDLE_REFRESH_S`.
    """
    now = time.monotonic()
    if now - _idle_time[0] < IDLE_REFRESH_S:
        return _idle_value[0]
    val: int | None
    try:
        runnable = _runnable_tasks()
        cpus = _usable_cpus()
        val = cpus - runnable        # the caller is one of the runnable tasks
        if val < 1 and runnable > 1:  # busy? unless the others are our own threads
            val = cpus - 1 - max(0, runnable - _own_running_threads())
    except (OSError, ValueError, IndexError):  # pragma: no cover - not Linux
        val = None
    _idle_time[0], _idle_value[0] = now, val
    return val


def profile_parallel(n_lines: int, n_samples: int) -> bool:
    """Whether a single profile of ``n_lines`` x ``n_samples`` should use the parallel kernels.

    Only where it pays: a large frame (:data:`PARALLEL_MIN_PIXELS`,
    :data:`PARALLEL_MIN_LINES`), outside :func:`serial_kernels`, more than one numba
    thread, and a core free for the second thread right now (:func:`idle_cpus`): when
    other processes hold the cores, a split frame waits for its slowest part (a thread
    the scheduler has put aside), while the serial kernel just takes its share.
    """
    if in_serial_context() or n_lines < PARALLEL_MIN_LINES or n_lines * n_samples < PARALLEL_MIN_PIXELS:
        return False
    nb = _numba()
    if nb is None or nb.get_num_threads() < 2:
        return False
    idle = idle_cpus()
    return idle is None or idle >= 1


def threading_info() -> dict:
    """What runs the threads: numba's layer (None before its first parallel kernel) and
    thread count, the OpenMP wait settings, OpenCV's thread count and parallel framework."""
    import cv2

    nb = _numba()
    layer = None
    if nb is not None:
        try:
            layer = nb.threading_layer()
        except ValueError:  # no parallel kernel has run yet
            layer = None
    fw = ""
    for line in cv2.getBuildInformation().splitlines():
        if "Parallel framework" in line:
            fw = line.split(":", 1)[1].strip()
    return {
        "numba_threading_layer": layer,
        "numba_layer_priority": list(nb.config.THREADING_LAYER_PRIORITY) if nb is not None else None,
        "numba_threads": nb.get_num_threads() if nb is not None else 0,
        "numba_max_threads": nb.config.NUMBA_NUM_THREADS if nb is not None else 0,
        "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY"),
        "KMP_BLOCKTIME": os.environ.get("KMP_BLOCKTIME"),
        "GOMP_SPINCOUNT": os.environ.get("GOMP_SPINCOUNT"),
        "omp_runtime_loaded_before": _OMP_PRELOADED,
        "blas_pools": _blas_pools(),
        "blas_setting": _blas_note[0],
        "opencv_threads": cv2.getNumThreads(),
        "opencv_parallel_framework": fw,
        "cpus_usable": _usable_cpus(),
        "idle_cpus_now": idle_cpus(),
    }


def describe() -> str:
    """:func:`threading_info` in one line."""
    i = threading_info()
    return (f"numba threading layer {i['numba_threading_layer']} (priority {i['numba_layer_priority']}), "
            f"numba threads {i['numba_threads']}/{i['numba_max_threads']}, OMP_WAIT_POLICY={i['OMP_WAIT_POLICY']}, "
            f"KMP_BLOCKTIME={i['KMP_BLOCKTIME']}, GOMP_SPINCOUNT={i['GOMP_SPINCOUNT']}, OpenMP runtime loaded before lightplane: "
            f"{i['omp_runtime_loaded_before'] or 'none'}; BLAS threads "
            f"{', '.join(f'{n} {t}' for n, t in i['blas_pools']) or 'none loaded'} ({i['blas_setting']}); OpenCV threads {i['opencv_threads']} "
            f"({i['opencv_parallel_framework']}); usable CPUs {i['cpus_usable']}, idle CPUs now {i['idle_cpus_now']}")
