"""fluorocal stages: pure functions from typed artifacts and frozen parameters to artifacts.

Stages never import the pipeline (the rest of :mod:`fluorocal`); they do no file I/O except in
:mod:`fluorocal.stages.io`.
Conventions (pixels, quaternions, units) are stated once in docs/concepts.md, "Conventions".
"""
