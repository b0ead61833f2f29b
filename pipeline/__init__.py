"""fluorocal pipeline: orchestration, cache, config, CLI, and the public :class:`Calibration` API.

``from fluorocal import Calibration`` is resolved lazily, so the CLI's ``--help`` imports nothing heavy.
"""


def __getattr__(name):
    if name == "Calibration":
        from fluorocal.calibration import Calibration

        return Calibration
    raise AttributeError(f"module 'fluorocal' has no attribute {name!r}")
