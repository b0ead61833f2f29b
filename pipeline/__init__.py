"""fluorocal pipeline: orchestration, cache, config, CLI, and the public :class:`Calibration` API.

``from pipeline import Calibration`` is resolved lazily, so the CLI's ``--help`` imports nothing heavy.
"""


def __getattr__(name):
    if name == "Calibration":
        from pipeline.calibration import Calibration

        return Calibration
    raise AttributeError(f"module 'pipeline' has no attribute {name!r}")
