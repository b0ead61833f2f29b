"""The attack battery: hostile and careless input, faults and tampering, run through the command line (issue 13).

One small simulated biplanar project (``fluorocal simulate --frames 4 --systems 2 --image-size 512 512``) is
run once so its cache is warm (:func:`tests.attack.harness.build_base`); then, per case, it is copied into a
folder of its own beside a ``sibling/`` folder (a user's other work), one hostile or careless change is applied
and the ``fluorocal`` command(s) a user would run are run, each in a subprocess. Per case it records:

- the exit code, and whether stdout/stderr hold a Python traceback (``--debug`` is never passed);
- whether a refusal is one clear line (``fluorocal: error: ...``) naming the file, key or argument;
- whether any file outside the project's output and cache folders (and the command's own ``--out``) was
  created, modified or deleted: the whole case folder, the project's inputs and the sibling included, is
  snapshotted before and after (type, size, mtime, sha256, link target);
- whether code from data ran: payloads that would ``touch`` a canary file;
- for a case that exits 0, whether the result is right: each case states its correct outcome (``refuse``,
  ``ok`` with a check against the clean run's results or the simulator's truth, or ``either``).

Targets (issue 13): 0 tracebacks, 0 silent wrong results, 0 files written or deleted outside the output and
cache folders, 0 code executed from data; and every refusal one clear line, no good input refused.

``tests/attack/test_attack.py`` runs each case as a test (``make check``); ``benchmarks/attack.py`` runs them
with per-case lines and totals (``--quick``, ``--only``, ``--list``, ``--jobs``, ``--keep``, ``--write-docs``).
The harness is :mod:`tests.attack.harness`, the cases are the tables of :mod:`tests.attack.cases`.
"""
