"""How a process that runs stages is set up: garbage collection, glibc's malloc, thread counts, Ctrl-C.

Speed and memory settings measured on this project's 2-core machine (stages/DECISIONS.md, engine):
full garbage collections made rare (:func:`quiet_full_collections`), freed arrays' memory kept for the
next ones instead of mapped and faulted in again (:func:`reuse_freed_memory`, and for the keypoints
network :func:`keep_network_memory`) but given back after a task that left more than
:data:`FREED_KEEP_BYTES` free (:func:`return_freed_memory`), one thread per task for torch and numba when two tasks share
the cores (:func:`pin_threads`), and SIGINT held while worker processes start so that Ctrl-C is
reported once, by the driver (:func:`sigint_held`). Standard library only: ``polyvec``'s launcher
imports it (:data:`THREAD_ENV`) before it forks the keypoints child (:mod:`.early_child`).
"""

from __future__ import annotations

import functools
import gc
import signal
import sys
import threading
from contextlib import contextmanager

#: One thread each for the numerical libraries of a process that runs beside another (dask's
#: workers, the keypoints child): read by them at import, so set before.
THREAD_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
              "NUMBA_NUM_THREADS": "1", "VECLIB_MAXIMUM_THREADS": "1"}

#: Young (generation-1) collections per full one in a process that runs stages; CPython's default is 10.
#: A full collection scans every live object: after hydra's, numba's and the stages' imports (~200,000
#: objects) each took ~0.1 s and found 10–90 unreachable objects. Six of them cost ~0.6 s of the
#: elephant's default run and four ~0.3 s of its λ re-run (stages/DECISIONS.md, engine). Young garbage
#: is still collected as often as before.
FULL_COLLECTION_EVERY = 1000


def quiet_full_collections() -> None:
    """Make full garbage collections rare in this process (:data:`FULL_COLLECTION_EVERY`)."""
    young, middle, _ = gc.get_threshold()
    gc.set_threshold(young, middle, FULL_COLLECTION_EVERY)


#: glibc's malloc serves a request of this many bytes or more with a fresh ``mmap`` and unmaps it on
#: ``free``, so the next array of that size is faulted in again page by page (the kernel zeroing
#: each page). Its threshold adapts from 128 KiB up to 32 MiB — unless a trim threshold is set, as dask
#: does in its workers (``MALLOC_TRIM_THRESHOLD_=65536``), which freezes it at 128 KiB: a 2-worker batch
#: of 8 drawings spent 3.5–4.8 of each worker's 13–14 CPU seconds in the kernel, 0.7–1.2 with this
#: (stages/DECISIONS.md, engine). 32 MiB, the largest glibc accepts on 64-bit, keeps a 2-Mpx
#: drawing's float64 arrays (16 MiB) in the heap.
HEAP_MMAP_BYTES = 32 * 2**20
#: Free memory at the top of the heap kept for the next array instead of given back: as much as the
#: largest array the heap serves (a worker's peak RSS on 24 drawings 707–728 → 823–872 MB; 256 MiB
#: gave 910 MB for no measurable time).
HEAP_TRIM_BYTES = 32 * 2**20
#: The keypoints child's trim threshold (:func:`keep_network_memory`): more than the network's
#: activations freed at once in one pass of a drawing of ``keypoints.single_pass_max`` px.
NETWORK_TRIM_BYTES = 2**30
#: Freed heap a process may carry from one task into the next (:func:`return_freed_memory`): more than
#: the 17–122 MB any stage left in the main process on two 512-px drawings and the 500×753 elephant
#: (one in-process run), so that their tasks still reuse it; less than
#: the 364 MB the field of a 6-Mpx page (4×4 scans) left in the main process, on top of which the graph
#: peaked (stages/DECISIONS.md, engine).
FREED_KEEP_BYTES = 192 * 2**20
_HEAP_TUNED = False
_FREED_KEEP = [FREED_KEEP_BYTES]   # this process's; the keypoints child keeps its network's heap
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX = -1, -3, -4      # glibc's <malloc.h>


@functools.lru_cache(maxsize=1)
def _glibc():
    """glibc's ``malloc_trim`` and ``mallinfo2`` (free bytes of every arena), or None where the C library
    has them not (not glibc, glibc before 2.33); looked up once."""
    import ctypes

    class MallInfo2(ctypes.Structure):
        _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd",
                                                         "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]

    try:
        libc = ctypes.CDLL(None)
        trim, info = libc.malloc_trim, libc.mallinfo2
    except (OSError, AttributeError, TypeError):
        return None
    trim.argtypes, trim.restype = (ctypes.c_size_t,), ctypes.c_int
    info.argtypes, info.restype = (), MallInfo2
    return trim, info


def freed_heap_bytes() -> int | None:
    """Bytes of this process's heap that malloc holds free (every arena's), None where unknown."""
    if (glibc := _glibc()) is None:
        return None
    return int(glibc[1]().fordblks)


def return_freed_memory(keep: int | None = None) -> bool:
    """Give the heap's free pages back to the system (glibc's ``malloc_trim``) when malloc holds more
    than ``keep`` bytes free (default :data:`FREED_KEEP_BYTES`, or :data:`NETWORK_TRIM_BYTES` after
    :func:`keep_network_memory`); True when it did.

    Called after each task: :func:`reuse_freed_memory` keeps freed arrays in the heap for the next ones,
    but a task on another thread allocates from another arena and cannot reuse them, and a stage of a
    large drawing may leave hundreds of MB free there that the next stage's peak then sits on (the
    field of a 6-Mpx page: 364 MB under the graph's peak). Below ``keep``, nothing (a small drawing's
    tasks keep reusing their heap). ``malloc_trim`` also returns free pages inside the heap, not only at
    its top.
    """
    if (glibc := _glibc()) is None or glibc[1]().fordblks <= (_FREED_KEEP[0] if keep is None else keep):
        return False
    glibc[0](0)
    return True


@functools.lru_cache(maxsize=1)
def _mallopt():
    """glibc's ``mallopt`` (None where the C library has none: not glibc); looked up once."""
    import ctypes

    try:  # the symbols already loaded into this process, the C library's among them
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError, TypeError):  # no mallopt (macOS), no CDLL(None) (Windows)
        return None
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    return mallopt


def reuse_freed_memory() -> None:
    """Make glibc's malloc keep freed arrays' memory for the next ones (:data:`HEAP_MMAP_BYTES`,
    :data:`HEAP_TRIM_BYTES`) in this process. Once per process; nothing where the C library has no
    ``mallopt`` (not glibc)."""
    global _HEAP_TUNED
    if _HEAP_TUNED:
        return
    _HEAP_TUNED = True
    if (mallopt := _mallopt()) is not None:
        mallopt(_M_MMAP_THRESHOLD, HEAP_MMAP_BYTES)
        mallopt(_M_TRIM_THRESHOLD, HEAP_TRIM_BYTES)


def keep_network_memory() -> None:
    """Serve every allocation of this process from the heap and keep up to :data:`NETWORK_TRIM_BYTES`
    of freed memory: for the keypoints child, whose network frees and allocates full-resolution
    activations layer after layer. At 704² a 32-channel map is 63 MB, above the 32-MiB ceiling of
    glibc's mmap threshold, so each was a fresh mapping faulted in page by page (54–139 k faults a
    pass; stages/DECISIONS.md, engine). A process's first pass faults its peak in either way; the
    passes after it (a multi-drawing run, a large drawing's tiles) reuse it. The child's memory stays
    at its peak until it exits."""
    reuse_freed_memory()
    # a 512-px drawing's pass leaves ~340 MB free: trimmed after each keypoints task, the next
    # drawing's pass would fault it in again
    _FREED_KEEP[0] = NETWORK_TRIM_BYTES
    if (mallopt := _mallopt()) is not None:
        mallopt(_M_MMAP_MAX, 0)
        mallopt(_M_TRIM_THRESHOLD, NETWORK_TRIM_BYTES)


def pin_threads(alone: bool = False) -> None:
    """One thread per task for torch and numba (worker processes also get THREAD_ENV at spawn).

    ``alone``: the task is the only one running (in-process): the flow may share its paths among
    ``numba.get_num_threads()`` threads (its results do not depend on their number); torch
    stays at one (the keypoints stage sets its own ``torch_threads``). NUMBA_NUM_THREADS is never
    changed in a running process: numba re-reads its environment when it compiles and refuses a
    value that differs from the thread pool it already launched.
    """
    # getattr: in-process, another task's thread may be importing torch or numba right now (the module
    # is in sys.modules before it is initialised); that task pins its own threads when it runs.
    set_torch = getattr(sys.modules.get("torch"), "set_num_threads", None)
    if set_torch is not None:
        set_torch(1)
    numba = sys.modules.get("numba")
    set_numba, config = getattr(numba, "set_num_threads", None), getattr(numba, "config", None)
    if set_numba is not None and config is not None:
        set_numba(config.NUMBA_NUM_THREADS if alone else 1)


@contextmanager
def sigint_held():
    """Ctrl-C held back while this thread starts worker processes, then raised once.

    SIGINT is blocked in this thread, so that the processes it starts and the threads it starts
    meanwhile (dask's event loop, which starts the nannies) inherit it blocked: the terminal sends
    Ctrl-C to the whole process group, and each worker would print its own tracebacks; the driver
    reports the interrupt once and shuts them down. A Ctrl-C pressed meanwhile (pending, or taken by
    an older thread of this process and recorded by a handler that only notes it) is raised as
    KeyboardInterrupt when the block ends. SIGINT used to be *ignored* here, which the workers
    inherited as well but which dropped a Ctrl-C pressed while a local cluster started: a folder's
    run went on to its end (stages/DECISIONS.md, engine). Elsewhere than the main thread, a no-op.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    # multiprocessing starts its resource tracker at the first spawn and *unblocks* SIGINT in the
    # spawning thread afterwards: started before the block, it leaves the block alone
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()
    pressed = []
    handler = signal.signal(signal.SIGINT, lambda signum, frame: pressed.append(signum))
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        if signal.SIGINT in signal.sigpending():
            signal.sigwait({signal.SIGINT})
            pressed.append(signal.SIGINT)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        # None: a handler not set from Python (embedding); Python's own is the sensible one back
        signal.signal(signal.SIGINT, handler if handler is not None else signal.default_int_handler)
    if pressed and handler is not signal.SIG_IGN:
        raise KeyboardInterrupt
