"""Which epochs train and which are held out, and the training subsets of each size (the paper's section VI).

The paper withholds half the images, uniformly sampled, and calibrates on
15, 30, 45, 60 and 75 of the remaining 75. Here an epoch (one exposure of
every system: a biplanar pair) is the unit, so a held-out epoch is held out
in every system.
"""

from __future__ import annotations

import numpy as np
from fluorocal.stages.errors import InputError

#: the keyword rules of :func:`heldout_epochs`
HOLDOUT_RULES = ("odd", "even", "random:SEED")

#: fewest training epochs a calibration is run on (one epoch leaves a free network without depth)
MIN_TRAIN = 2


def min_train_epochs(n_systems: int, min_exposures: int = 3) -> int:
    """Fewest training epochs: :data:`MIN_TRAIN`, and enough frames for the adjustment's ``min_exposures``.

    Examples
    --------
    >>> min_train_epochs(1), min_train_epochs(2)
    (3, 2)
    """
    return max(MIN_TRAIN, -(-min_exposures // n_systems))


def heldout_epochs(epochs, rule: str) -> np.ndarray:
    """The epochs a keyword ``rule`` withholds from ``epochs`` (sorted unique ints).

    ``"odd"`` withholds every other epoch starting with the second (in sorted
    order), ``"even"`` every other starting with the first, ``"random:SEED"``
    half of them (rounded down) drawn with ``np.random.default_rng(SEED)``.

    Raises
    ------
    InputError
        An unknown rule or seed.

    Examples
    --------
    >>> heldout_epochs([0, 1, 2, 3, 4], "odd").tolist()
    [1, 3]
    >>> heldout_epochs([0, 1, 2, 3, 4], "even").tolist()
    [0, 2, 4]
    >>> len(heldout_epochs(range(10), "random:3"))
    5
    """
    epochs = np.unique(np.asarray(list(epochs), dtype=np.int64))
    if rule == "odd":
        return epochs[1::2]
    if rule == "even":
        return epochs[0::2]
    kind, _, seed = rule.partition(":")
    if kind == "random" and seed.isascii() and seed.isdigit():
        rng = np.random.default_rng(int(seed))
        return np.sort(rng.choice(epochs, size=len(epochs) // 2, replace=False))
    raise InputError(
        f"--holdout must be one of {', '.join(HOLDOUT_RULES)} (SEED a non-negative integer) or frame files; "
        f"got {rule!r}"
    )


def default_train_sizes(n_train: int, n_sizes: int = 5, minimum: int = MIN_TRAIN) -> tuple[int, ...]:
    """``n_sizes`` training sizes evenly spaced up to ``n_train`` (the paper's 15, ..., 75 of 75), each >= ``minimum``.

    Empty when ``n_train < minimum``.

    Examples
    --------
    >>> default_train_sizes(75)
    (15, 30, 45, 60, 75)
    >>> default_train_sizes(3)
    (2, 3)
    """
    sizes = {max(minimum, round(n_train * k / n_sizes)) for k in range(1, n_sizes + 1)}
    return tuple(sorted(s for s in sizes if s <= n_train))


def check_train_sizes(sizes, n_train: int, minimum: int = MIN_TRAIN, *, why: str = "") -> tuple[int, ...]:
    """``sizes`` sorted and unique, refused (:class:`InputError`) when empty or outside ``minimum..n_train``.

    ``why``: what limits the sizes, said in the refusal (default: the training epochs after the holdout).
    """
    sizes = tuple(sorted(set(int(s) for s in sizes)))
    if not sizes:
        raise InputError("--train-sizes is empty; give comma-separated counts of training epochs")
    if sizes[0] < minimum or sizes[-1] > n_train:
        bad = sizes[0] if sizes[0] < minimum else sizes[-1]
        why = why or (
            f"the project has {n_train} training epoch(s) after the holdout; a calibration needs at least {minimum}"
        )
        raise InputError(f"--train-sizes: {bad} is outside {minimum}..{n_train} ({why})")
    return sizes


def training_subset(train_epochs, size: int) -> np.ndarray:
    """``size`` of the sorted ``train_epochs``, evenly spaced over them (first and last included when size > 1).

    Examples
    --------
    >>> training_subset([0, 2, 4, 6, 8, 10], 3).tolist()
    [0, 4, 10]
    """
    train = np.unique(np.asarray(list(train_epochs), dtype=np.int64))
    if not 1 <= size <= len(train):
        raise InputError(f"training size {size} is outside 1..{len(train)}")
    return train[np.round(np.linspace(0, len(train) - 1, size)).astype(int)]


__all__ = [
    "HOLDOUT_RULES",
    "MIN_TRAIN",
    "heldout_epochs",
    "default_train_sizes",
    "check_train_sizes",
    "training_subset",
]
