"""A three-step pipeline in bounded memory: a reader thread, the calling thread, a writer thread.

``fluorocal undistort`` reads, remaps and writes frames at once: OpenCV and the file reads
release the GIL, so decoding the next frame, remapping this one and encoding the last one
overlap. Between the steps, queues of ``depth`` items bound the frames held in memory to about
``2 * depth + 3``, whatever the number of frames.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterable, Iterator

#: the end of the items (or a step that stopped)
_END = object()
#: seconds between looks at the stop flag while a queue is full or empty
_POLL_S = 0.05


class _Pipe:
    """Bounded queues and a stop flag that every step watches, so that no step blocks after another failed."""

    def __init__(self, depth: int):
        self.read_q: queue.Queue = queue.Queue(depth)
        self.write_q: queue.Queue = queue.Queue(depth)
        self.stop = threading.Event()
        self.failures: list[BaseException] = []

    def fail(self, exc: BaseException) -> None:
        self.failures.append(exc)
        self.stop.set()

    def put(self, q: queue.Queue, item) -> bool:
        while not self.stop.is_set():
            try:
                q.put(item, timeout=_POLL_S)
                return True
            except queue.Full:
                pass
        return False

    def drain(self, q: queue.Queue) -> Iterator:
        """The items of ``q`` until its end, or until a step fails."""
        while not self.stop.is_set():
            try:
                item = q.get(timeout=_POLL_S)
            except queue.Empty:
                continue
            if item is _END:
                return
            yield item


def stream(items: Iterable, transform: Callable, consume: Callable[[Iterator], None], *, depth: int = 4) -> None:
    """Run ``consume(transform(item) for item in items)`` with reading, transforming and consuming overlapped.

    Parameters
    ----------
    items : iterable
        Iterated in a reader thread (reading frames from disk).
    transform : callable
        Applied in the calling thread, in order (remapping, progress).
    consume : callable (iterator) -> None
        Run in a writer thread over the transformed items, in order (writing files).
    depth : int
        Items each of the two queues holds at most.

    Raises
    ------
    BaseException
        The first exception of any step, after every step has stopped. ``consume`` then sees its
        iterator end early: a writer must refuse to commit a file short of frames.

    Examples
    --------
    >>> out = []
    >>> stream(range(5), lambda x: x * x, out.extend, depth=2)
    >>> out
    [0, 1, 4, 9, 16]
    """
    pipe = _Pipe(depth)

    def read():
        try:
            for item in items:
                if not pipe.put(pipe.read_q, item):
                    return
        except BaseException as exc:  # every failure, re-raised in the calling thread
            pipe.fail(exc)
        finally:
            pipe.put(pipe.read_q, _END)

    def write():
        try:
            consume(pipe.drain(pipe.write_q))
        except BaseException as exc:
            pipe.fail(exc)
        finally:
            pipe.stop.set()  # done (or stopped early): nothing may wait on the queues any more

    threads = [threading.Thread(target=read, daemon=True), threading.Thread(target=write, daemon=True)]
    for thread in threads:
        thread.start()
    try:
        for item in pipe.drain(pipe.read_q):
            if not pipe.put(pipe.write_q, transform(item)):
                break
        pipe.put(pipe.write_q, _END)
    except BaseException as exc:
        pipe.fail(exc)
    finally:
        for thread in reversed(threads):  # the writer sets the stop flag when it ends, which ends the reader
            thread.join()
    if pipe.failures:
        raise pipe.failures[0]
