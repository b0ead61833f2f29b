"""The lattices a grid plate may have, by their spelling in ``[phantom] lattice``: ``"hex"``, ``"square"``.

The spellings alone, apart from the lattices' geometry (:mod:`fluorocal.stages.label.lattice`), so that the
kinds' table (:data:`fluorocal.stages.kinds.KINDS`), and through it the config and the command line, read
them without importing the labelling: ``fluorocal --help`` stays instant.
"""

#: the lattices a grid plate may have, by their spelling in ``[phantom] lattice``
LATTICES = ("hex", "square")
