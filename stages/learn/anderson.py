"""Anderson acceleration of the alternation's fixed-point iteration, as a value passed in and returned."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class Anderson:
    """The memory of Anderson acceleration (type II, Walker & Ni 2011) of ``x <- g(x)``.

    :func:`anderson_step` returns the next iterate and the updated memory.
    Only the entries selected by ``mask`` at the first step after a restart
    (the grid nodes the data support) are combined; the others take the plain
    step, since nodes far from all data barely change the cost and would only
    add noise to the least-squares combination. :meth:`restarted` forgets the
    history (after a step that raised the cost); :func:`anderson_step` forgets
    it too when the residual ``g - x`` has grown since the last step.

    Attributes
    ----------
    depth : int
        Past iterates combined.
    x, g : (M,) float64 ndarray or None
        The last iterate and its image, at the masked entries.
    mask : (N,) bool ndarray or None
    dF, dG : tuple of (M,) float64 ndarray
        Differences of the residuals ``g - x`` and of the images, newest last.

    Examples
    --------
    >>> acc = Anderson(depth=2)
    >>> x = np.array([1.0])
    >>> for _ in range(3):
    ...     x, acc = anderson_step(acc, x, 0.5 * x + 1)  # fixed point 2
    >>> round(float(x[0]), 6)
    2.0
    """

    depth: int
    x: np.ndarray | None = None
    g: np.ndarray | None = None
    mask: np.ndarray | None = None
    dF: tuple = ()
    dG: tuple = ()

    def restarted(self) -> "Anderson":
        """The same depth, no history."""
        return Anderson(self.depth)


def anderson_step(
    memory: Anderson, x: np.ndarray, g: np.ndarray, mask: np.ndarray | None = None
) -> tuple[np.ndarray, Anderson]:
    """The accelerated next iterate from ``x`` and its image ``g = g(x)``, and the memory after it.

    A residual ``g - x`` larger than the last one's means the last combination did not help: near the
    fixed point of an inexactly evaluated map (the learning's inner solves) the differences are mostly
    noise, which the combination amplifies. The history is forgotten then and the step is the plain one.
    """
    keep = memory.mask
    if keep is None:
        keep = np.ones(len(x), bool) if mask is None else np.asarray(mask, bool).copy()
    out = g.copy()
    xm, gm = x[keep], g[keep]
    f = gm - xm
    if memory.x is not None and np.linalg.norm(f) > np.linalg.norm(memory.g - memory.x):
        memory = replace(memory, x=None, g=None, dF=(), dG=())
    dF, dG = memory.dF, memory.dG
    if memory.x is not None:
        dF = (dF + (f - (memory.g - memory.x),))[-memory.depth :]
        dG = (dG + (gm - memory.g,))[-memory.depth :]
    if dF:
        dF_mat = np.column_stack(dF)
        dG_mat = np.column_stack(dG)
        # Tikhonov-regularised least squares keeps the combination bounded when the differences are collinear
        lam = 1e-10 * float(np.sum(dF_mat * dF_mat))
        gamma = np.linalg.solve(dF_mat.T @ dF_mat + lam * np.eye(dF_mat.shape[1]), dF_mat.T @ f)
        out[keep] = gm - dG_mat @ gamma
    return out, replace(memory, x=xm, g=gm, mask=keep, dF=dF, dG=dG)


__all__ = ["Anderson", "anderson_step"]
