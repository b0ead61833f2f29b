"""How a table of the attack battery registers its cases: :meth:`Catalogue.add`, in the order they run."""

from __future__ import annotations

from tests.attack.checks import same_as_clean
from tests.attack.harness import Case, run_cfg


class Catalogue(list):
    """The cases of one table (or of the battery), in the order they were added."""

    def add(self, name, klass, setup, commands=run_cfg, expect="refuse", hints=(), check=None, allow=(), **kw) -> Case:
        """Add a case; one that may exit 0 without its own check is checked against the clean run's results."""
        if expect in ("ok", "either") and check is None:
            check = same_as_clean
        case = Case(name, klass, setup, commands, expect, tuple(hints), check, tuple(allow), **kw)
        self.append(case)
        return case
