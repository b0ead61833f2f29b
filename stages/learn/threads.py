"""Each system's independent work in the learning: one system after the other, or side by side in threads.

A biplanar project's two systems share the loop's adjustment, but much of each iteration is a system's own:
its kNN regression, its gross-error screen, its smoothness cross-validation, its joint uncertainty. Given
``workers`` > 1 by the caller (the pipeline passes its worker count, ``--jobs``), :func:`each_system` runs
these in up to that many threads, with one BLAS thread each as the process was started with; the numbers are
those of the serial run (each system's work reads only its own data and writes nothing shared). One system,
or ``workers=1`` (the default, as a library call and the tests get it), starts no thread at all.

Threads, not processes: the work is NumPy, BLAS and the KD-tree's queries, which release the GIL, on arrays
that would otherwise be copied to another process.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable


def each_system(function: Callable, n_systems: int, workers: int = 1) -> tuple:
    """``(function(0), ..., function(n_systems - 1))``, side by side in up to ``workers`` threads.

    An exception of ``function`` is raised as the serial loop would raise it: the first system's (in system
    order) that fails. The threads end before this returns or raises (a Ctrl-C included: after the systems
    being computed finish, the others are not started).
    """
    if workers < 2 or n_systems < 2:
        return tuple(function(s) for s in range(n_systems))
    with ThreadPoolExecutor(min(workers, n_systems), thread_name_prefix="fluorocal-system") as pool:
        futures = [pool.submit(function, s) for s in range(n_systems)]
        try:
            return tuple(future.result() for future in futures)
        finally:
            for future in futures:
                future.cancel()


__all__ = ["each_system"]
