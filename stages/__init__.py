"""fluorocal stages: pure functions from typed artifacts and frozen parameters to artifacts.

Stages never import :mod:`pipeline`; they do no file I/O except in :mod:`stages.io`.
Conventions (pixels, quaternions, units) are stated once in README.md, "Conventions".
"""
