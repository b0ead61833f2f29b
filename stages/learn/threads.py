"""Each system's independent work in the learning: one system after the other, or side by side in threads.

A biplanar project's two systems share the loop's adjustment, but their regressions (the kNN's, the refinement's
smoothness cross-validations) and their joint uncertainties
(:func:`~fluorocal.stages.learn.uncertainty.learned_uncertainty`) are each system's own: given ``workers`` > 1 by
the caller (the pipeline passes its worker count, ``--jobs``), :func:`each_system` runs the systems in up to that
many threads, with one BLAS thread each as the process was started with; the numbers are those of the serial
run (each system's work reads only its own data and writes nothing shared). One system, or ``workers=1`` (the
default, as a library call and the tests get it), starts no thread at all.

Threads, not processes: that work is mostly compiled code that releases the GIL, on arrays that would otherwise
be copied to another process: BLAS-3 products and LAPACK's Cholesky factorizations and solves
(:mod:`.nogil`: SciPy's own wrappers hold the GIL) and the KD-tree's queries. The refinement's joint field step
couples the systems and stays serial.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable


def each_system(function: Callable, n_systems: int, workers: int = 1) -> tuple:
    """``(function(0), ..., function(n_systems - 1))``, side by side in up to ``workers`` threads.

    An exception of ``function`` is raised as the serial loop would raise it: the first system's (in system
    order) that fails. The threads end before this returns or raises (a Ctrl-C included: after the systems
    being computed finish, the others are not started).

    Examples
    --------
    >>> each_system(lambda s: s * s, 3, workers=2)
    (0, 1, 4)
    """
    if workers < 2 or n_systems < 2:
        return tuple(function(s) for s in range(n_systems))
    pool = ThreadPoolExecutor(min(workers, n_systems), thread_name_prefix="fluorocal-system")
    try:
        futures = [pool.submit(function, s) for s in range(n_systems)]
        return tuple(future.result() for future in futures)
    finally:  # a Ctrl-C while submitting too: the systems not yet started never are, the running ones end
        pool.shutdown(wait=True, cancel_futures=True)


__all__ = ["each_system"]
