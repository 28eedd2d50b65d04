"""One BLAS thread per process where a stage's processes share the cores.

A stage that fans out runs one worker process per core; OpenBLAS's default of one thread per
core in each of them puts twice as many threads as cores on the small factorisations the
stages do per unit (a unit's trend, a Kriging model of a few hundred points), and they
then wait on each other: on two busy cores a 240 x 240 Cholesky factorisation took
4-16 ms with OpenBLAS's threads against 0.6 ms in one. The worker processes are forked with
numpy already loaded (a process pool) or started by a Dask nanny, so an environment
variable set now would come too late: :mod:`threadpoolctl` sets the loaded libraries' own
thread counts (numpy's and scipy's OpenBLAS, OpenMP) instead. Single-threaded or not, the
libraries give the same bits: a factorisation or product splits its output, not its sums,
between threads.
"""
from __future__ import annotations


#: What OpenBLAS, OpenMP and MKL read when they are loaded.
THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread():
    """Limit this process's BLAS and OpenMP libraries to one thread.

    Called as it is (a pool worker's set-up), the limit holds for the process's life; used
    as a context manager (``with one_blas_thread():``, a stage's in-process path), the
    libraries' thread counts are restored on leaving the block. threadpoolctl reaches only
    the libraries loaded when it is called: numpy's and scipy's (each wheel ships its own
    OpenBLAS) are loaded first."""
    import numpy.linalg  # noqa: F401
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits
    return threadpool_limits(limits=1)


def one_blas_thread_for_good() -> None:
    """One BLAS and OpenMP thread for the rest of a worker process's life: the libraries
    loaded already limited, those it loads later (scipy's OpenBLAS in a worker that only
    runs an FMU until then) by their thread variables, set before they read them."""
    import os

    from threadpoolctl import threadpool_limits
    for name in THREAD_VARIABLES:
        os.environ[name] = "1"
    threadpool_limits(limits=1)
