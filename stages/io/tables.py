"""CSV tables: one declarative schema per table, one reader and one writer for all of them.

Every table fluorocal reads or writes is a :class:`Table` of :class:`Column` s
below (:data:`TABLES`). :func:`read_table` checks the header, parses every
cell by its column's type and names the file, line and column of anything it
cannot use; :func:`write_table` writes the columns given, in the schema's
order, atomically. Columns the schema does not know are ignored on reading
and refused on writing. Units: px with the top-left pixel centre at (0, 0),
x right, y down; mm in the phantom's frame.
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from fluorocal.stages.errors import InputError
from fluorocal.stages.io.atomic import atomic_write

_NUMPY_DTYPE = {int: np.int64, float: np.float64, bool: np.bool_, str: np.str_}
_FALSE = ("0", "false", "no")
#: most beads a phantom file may hold: real phantoms have hundreds to a few thousand
MAX_PHANTOM_BEADS = 100_000
_LINE = "\0line"  # the record's line, kept beside the columns while reading
#: a phantom smaller than this (mm) on every axis, or with beads closer than this, was not written in mm
_MIN_PHANTOM_EXTENT_MM = 1.0
#: bead diameters below this (mm) cannot be imaged: a diameter in metres
_MIN_BEAD_DIAMETER_MM = 0.1
#: no fluoroscope images an object larger than this (mm): a larger phantom was written in a smaller unit
_MAX_PHANTOM_EXTENT_MM = 2000.0


@dataclass(frozen=True)
class Column:
    """One column of a CSV table.

    Attributes
    ----------
    name : str
        The header name.
    dtype : {int, float, bool, str}
        Cell type. Booleans are written ``1``/``0`` and read false from ``0``, ``false`` or ``no``.
    unit : str
        ``px``, ``mm``, ``rad`` or ``""``; documentation only.
    required : bool
        A file without this column is refused; an empty cell is refused.
    default : object
        For an optional column: the value of an empty cell, and of every row when the column is absent.
        ``None``: an absent column is left out of what :func:`read_table` returns.
    digits : int or None
        Float columns: decimals written; ``None`` writes the shortest text that reads back the same float64.
    aliases : tuple of str
        Older header names accepted on reading.
    choices : tuple of str
        Text columns: the values allowed besides the empty cell, matched in any case and read in lower case.
    """

    name: str
    dtype: type = float
    unit: str = ""
    required: bool = True
    default: object = None
    digits: int | None = None
    aliases: tuple[str, ...] = ()
    choices: tuple[str, ...] = ()

    def parse(self, text: str):
        """The value of one cell (stripped text); ``ValueError`` when it is not of the column's type."""
        if self.dtype is bool:
            return text.lower() not in _FALSE
        if self.choices:
            if text.lower() not in self.choices:
                raise ValueError(f"{text!r} is not one of {self.choices}")
            return text.lower()
        value = self.dtype(text)
        if self.dtype is int and not -(2**63) <= value < 2**63:
            raise ValueError(f"{text} does not fit in 64 bits")
        return value

    def format(self, value) -> str:
        """The text of one cell."""
        if self.dtype is float:
            value = float(value)
            return repr(value) if self.digits is None else f"{value:.{self.digits}f}"
        if self.dtype is bool:
            return "1" if value else "0"
        return str(int(value)) if self.dtype is int else str(value)

    def format_all(self, values) -> list[str]:
        """The texts of a column's cells: :meth:`format` of each, numeric arrays converted in one call.

        ``tolist`` gives the Python floats and ints ``float(v)`` and ``int(v)`` give, so the text is the same;
        formatting a numpy scalar at a time took most of writing ``observations.csv``.
        """
        array = np.asarray(values) if len(values) else None
        if array is None or array.ndim != 1:
            return [self.format(v) for v in values]
        if self.dtype is float and array.dtype.kind in "fiu":
            plain = array.astype(np.float64).tolist()
            return list(map(repr, plain)) if self.digits is None else [f"{v:.{self.digits}f}" for v in plain]
        if self.dtype is int and array.dtype.kind in "iu":
            return list(map(str, array.tolist()))
        return [self.format(v) for v in values]


@dataclass(frozen=True)
class Table:
    """A CSV table: its name (for messages) and its columns, in the order they are written."""

    name: str
    columns: tuple[Column, ...]

    def __post_init__(self):
        names = [c.name for c in self.columns]
        if len(set(names)) != len(names):
            raise InputError(f"table {self.name}: column names repeat: {names}")

    def column(self, name: str) -> Column:
        """The column called ``name``."""
        for c in self.columns:
            if c.name == name:
                return c
        raise InputError(f"table {self.name} has no column {name!r}; it has {','.join(self.names)}")

    @property
    def names(self) -> list[str]:
        """Every column name, in order."""
        return [c.name for c in self.columns]

    def describe(self) -> str:
        """The required columns, then the optional ones in brackets: ``id,x,y,z [diameter,role]``."""
        optional = ",".join(c.name for c in self.columns if not c.required)
        return ",".join(c.name for c in self.columns if c.required) + (f" [{optional}]" if optional else "")


def _f(name: str, unit: str, **kw) -> Column:
    return Column(name, float, unit, **kw)


def _opt(name: str, dtype: type, default, unit: str = "", **kw) -> Column:
    return Column(name, dtype, unit, required=False, default=default, **kw)


#: phantom bead centres (``[phantom] file``; ``fluorocal simulate`` writes it with reference.csv)
PHANTOM = Table(
    "phantom",
    (
        Column("id", int),
        _f("x", "mm", digits=6),
        _f("y", "mm", digits=6),
        _f("z", "mm", digits=6),
        _opt("diameter", float, math.nan, "mm", digits=6),
        _opt("role", str, "", choices=("marker",)),
    ),
)
#: manual seeds of the labelling (rows without a file belong to the first frame)
SEEDS = Table(
    "seeds",
    (Column("id", int), _f("x", "px", digits=6), _f("y", "px", digits=6), _opt("file", str, ""), _opt("frame", int, 0)),
)
#: fitted beads of single frames, written by ``fluorocal detect``, read by ``fluorocal label``
DETECTIONS = Table(
    "detections",
    (
        Column("file", str),
        Column("frame", int),
        _f("x", "px"),
        _f("y", "px"),
        _f("sigma_x", "px"),
        _f("sigma_y", "px"),
        _f("rho", ""),
        _f("major", "px"),
        _f("minor", "px"),
        _opt("angle", float, math.nan, "rad"),
        _opt("fit_rmse", float, math.nan, "px"),
        _opt("score", float, math.nan),
        _opt("ok", bool, True),
    ),
)
#: labelled bead centres: ``fluorocal label`` writes file..rho; ``fluorocal run`` (observations.csv and the
#: label stage's table) adds system, exposure, the correction Δ, residuals and inlier; ``fluorocal adjust``
#: reads any of these and writes them back with its own adjustment statistics
OBSERVATIONS = Table(
    "observations",
    (
        _opt("system", str, "A"),
        Column("file", str),
        _opt("frame", int, 0),
        _opt("exposure", int, None),
        Column("id", int),
        _f("x", "px"),
        _f("y", "px"),
        _f("sigma_x", "px"),
        _f("sigma_y", "px"),
        _f("rho", ""),
        _opt("delta_x", float, 0.0, "px", aliases=("dx",)),
        _opt("delta_y", float, 0.0, "px", aliases=("dy",)),
        _opt("residual_x", float, None, "px", aliases=("rx",)),
        _opt("residual_y", float, None, "px", aliases=("ry",)),
        _opt("wx", float, None),
        _opt("wy", float, None),
        _opt("redx", float, None),
        _opt("redy", float, None),
        _opt("weight", float, None),
        _opt("inlier", bool, None),
        _opt("used", bool, None),
    ),
)
#: what ``fluorocal label`` writes: the observations table's file, frame, id, x, y, sigma_x, sigma_y, rho
LABELS = OBSERVATIONS
#: adjusted bead centres and their standard deviations (``fluorocal run`` and ``fluorocal adjust``)
OBJECT_POINTS = Table(
    "object_points",
    (Column("id", int), *(_f(n, "mm", digits=6) for n in ("x", "y", "z", "sx", "sy", "sz"))),
)
#: every table schema
TABLES: tuple[Table, ...] = (PHANTOM, SEEDS, DETECTIONS, OBSERVATIONS, OBJECT_POINTS)


def _header_map(path: Path, table: Table, header: list[str]) -> dict[str, str]:
    """Schema column name -> the header name it has in this file; refuses a file missing a required column."""
    found = {}
    for c in table.columns:
        name = next((n for n in (c.name, *c.aliases) if n in header), None)
        if name is not None:
            found[c.name] = name
    missing = [c.name for c in table.columns if c.required and c.name not in found]
    if missing:
        raise InputError(f"{path}: {table.name} CSV needs columns {table.describe()}; missing {','.join(missing)}")
    return found


def _check_header(path: Path, table: Table, header: list[str], line_no: int) -> None:
    """Refuse a header naming a column twice (also under its two names, ``dx`` and ``delta_x``)."""
    seen: dict[str, str] = {}
    for name in header:
        column = next((c.name for c in table.columns if name in (c.name, *c.aliases)), name)
        if name and column in seen:
            also = "" if seen[column] == name else f" (as {seen[column]!r} and {name!r})"
            raise InputError(f"{path}:{line_no}: column {column} appears twice in the header{also}; keep one")
        seen[column] = name


def _parse_cell(path: Path, line_no: int, column: Column, text: str):
    if not text:
        if column.required or column.default is None:  # a column without a default has a value in every row
            raise InputError(f"{path}:{line_no}: empty cell in column {column.name}")
        return column.default
    try:
        return column.parse(text)
    except ValueError:
        kind = "an integer" if column.dtype is int else "a number"
        if column.choices:
            kind = " or ".join(repr(c) for c in column.choices) + " (in any case) or empty"
        raise InputError(f"{path}:{line_no}: not {kind} in column {column.name}: {text!r}") from None


def read_table(
    path: str | os.PathLike, table: Table, *, max_rows: int | None = None, lines: bool = False
) -> dict[str, np.ndarray]:
    r"""Read a CSV file by its schema: one array per column.

    Parameters
    ----------
    path : path-like
        The CSV file (a header row, then one row per record).
    table : Table
        Its schema.
    max_rows : int, optional
        Refuse a file with more records than this (read no further).
    lines : bool
        Also return each record's line in the file (blank lines counted) as ``"line"``,
        for messages about a record found wrong after reading.

    Returns
    -------
    dict of str to (N,) ndarray
        Every column of the schema present in the file, and every absent optional
        column that has a default (filled with it), under the schema's names.

    Raises
    ------
    InputError
        The file is missing, a folder, unreadable or not UTF-8 text (a byte-order mark is allowed),
        has more than ``max_rows`` records, lacks a required column or names one twice, has a row
        with more or fewer values than the header, or has a cell that is empty in a required column
        or not of its column's type (naming file, line and column).

    Examples
    --------
    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     _ = (Path(d) / "p.csv").write_text("id,x,y,z\n7,1.5,0,-2\n")
    ...     t = read_table(Path(d) / "p.csv", PHANTOM)
    >>> t["id"], t["z"], t["role"]
    (array([7]), array([-2.]), array([''], dtype='<U1'))
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder; a {table.name} CSV file is expected")
    if not path.is_file():
        raise InputError(f"{path}: {table.name} file not found")
    try:
        values = _read_rows(path, table, max_rows)
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not UTF-8 text (byte {exc.object[exc.start]:#04x}); save it as UTF-8 CSV") from None
    except csv.Error as exc:
        raise InputError(f"{path}: not a readable CSV file ({exc})") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    line = values.pop(_LINE)
    n_rows = len(line)
    out = {"line": np.array(line, dtype=np.int64)} if lines else {}
    for c in table.columns:
        if c.name in values:
            out[c.name] = np.array(values[c.name], dtype=_NUMPY_DTYPE[c.dtype])
        elif c.default is not None:
            out[c.name] = np.array([c.default] * n_rows, dtype=_NUMPY_DTYPE[c.dtype])
    return out


def _read_rows(path: Path, table: Table, max_rows: int | None) -> dict[str, list]:
    """Every record's cells, parsed, per schema column present in the file."""
    with open(path, newline="", encoding="utf-8-sig") as fh:  # utf-8-sig: a spreadsheet's byte-order mark
        reader = csv.DictReader(fh)
        header = [h.strip() for h in (reader.fieldnames or [])]
        _check_header(path, table, header, reader.line_num)
        found = _header_map(path, table, header)
        present = [table.column(n) for n in found]
        values: dict[str, list] = {c.name: [] for c in present}
        values[_LINE] = []
        for n_rows, row in enumerate(reader, start=1):
            line_no = reader.line_num  # the file's own line: blank lines (skipped) counted
            if max_rows is not None and n_rows > max_rows:
                raise InputError(f"{path}: more than {max_rows} {table.name} rows; is this the right file?")
            n_values = len(header) + len(row.get(None, ())) - sum(v is None for v in row.values())
            if n_values != len(header):  # a cell too many or too few shifts every column after it
                raise InputError(
                    f"{path}:{line_no}: {n_values} values in a row under a header of {len(header)} columns "
                    f"({','.join(header)}); give every row one value per column (empty for none)"
                )
            row = {k.strip(): (v.strip() if isinstance(v, str) else "") for k, v in row.items() if k is not None}
            values[_LINE].append(line_no)
            for c in present:
                values[c.name].append(_parse_cell(path, line_no, c, row.get(found[c.name], "")))
    return values


def write_table(path: str | os.PathLike, table: Table, columns: Mapping[str, Sequence]) -> None:
    """Write columns of a table atomically, in the schema's column order.

    Parameters
    ----------
    path : path-like
        The CSV file to write.
    table : Table
        Its schema.
    columns : mapping of str to sequence
        Column name -> one value per row; every required column, any optional ones.

    Raises
    ------
    InputError
        A column the schema does not know, a required one missing, or columns of different lengths.
    """
    unknown = [n for n in columns if n not in table.names]
    missing = [c.name for c in table.columns if c.required and c.name not in columns]
    if unknown or missing:
        raise InputError(
            f"{path}: {table.name} table: unknown column(s) {','.join(unknown) or '-'}; "
            f"missing {','.join(missing) or '-'}"
        )
    present = [c for c in table.columns if c.name in columns]
    lengths = {c.name: len(columns[c.name]) for c in present}
    if len(set(lengths.values())) > 1:
        raise InputError(f"{path}: {table.name} table: columns differ in length: {lengths}")
    cells = [c.format_all(columns[c.name]) for c in present]

    def _write(tmp):
        with open(tmp, "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow([c.name for c in present])
            w.writerows(zip(*cells))

    atomic_write(path, _write)


def columns_of(header: Sequence[str], rows) -> dict[str, tuple]:
    """Rows (one sequence per record, in ``header`` order) as :func:`write_table`'s columns.

    Examples
    --------
    >>> columns_of(["id", "x"], [[1, 0.5], [2, 1.5]])
    {'id': (1, 2), 'x': (0.5, 1.5)}
    >>> columns_of(["id", "x"], [])
    {'id': (), 'x': ()}
    """
    rows = list(rows)
    return {name: tuple(r[k] for r in rows) for k, name in enumerate(header)}


def write_csv(path: str | os.PathLike, header: list[str], rows) -> None:
    """Write a CSV table without a schema atomically (:func:`csv_text`), e.g. a cache entry's table."""
    data = csv_text(header, rows).encode("utf-8")
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(data))


#: the text of a cell of these exact types (floats with 6 decimals), as ``csv`` writes it: never quoted
_PLAIN_CELL = {int: "%d", float: "%.6f"}


def csv_text(header: list[str], rows) -> str:
    r"""A CSV table without a schema as text (``csv``'s default dialect): floats with 6 decimals, the rest ``str``.

    A row of plain ints and floats is formatted in one step, by a format string made once per row layout
    (the same text as the cell by cell ``csv`` writer gives: such cells need no quoting).

    Examples
    --------
    >>> csv_text(["id", "x", "name"], [[1, 0.5, "a,b"], [2, 1.25, "c"], [3, 2.0]])
    'id,x,name\r\n1,0.500000,"a,b"\r\n2,1.250000,c\r\n3,2.000000\r\n'
    """

    def fmt(v):
        return f"{v:.6f}" if isinstance(v, (float, np.floating)) else str(v)

    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow(header)
    lines: dict[tuple, str] = {}
    for row in rows:
        row = tuple(row)  # an iterator read once: its types, then its cells
        kinds = tuple(map(type, row))
        line = lines.get(kinds)
        if line is None:
            plain = kinds and all(k in _PLAIN_CELL for k in kinds)
            line = ",".join(_PLAIN_CELL[k] for k in kinds) + writer.dialect.lineterminator if plain else ""
            lines[kinds] = line
        if line:
            out.write(line % row)
        else:
            writer.writerow([fmt(v) for v in row])
    return out.getvalue()


def read_phantom(path: str | os.PathLike, *, lattice: str = "", pitch_mm: float = 0.0):
    """Read a phantom CSV ``id,x,y,z[,diameter][,role]`` (mm) as a :class:`~fluorocal.stages.artifacts.Phantom`.

    At most :data:`MAX_PHANTOM_BEADS` beads; a bead phantom (no ``lattice``) at least
    :data:`~fluorocal.stages.artifacts.MIN_PHANTOM_BEADS`. Coordinates must be finite; diameters
    finite and positive where given. A phantom whose size says it was written in
    metres or inches (:func:`check_phantom_units`) is refused with the guess.

    Raises
    ------
    InputError
        Missing file, missing column, a value that is not a number or not finite (naming the line),
        too many beads, or coordinates that are not in mm.
    """
    from fluorocal.stages.artifacts import MIN_PHANTOM_BEADS, Phantom

    t = read_table(path, PHANTOM, max_rows=MAX_PHANTOM_BEADS, lines=True)
    if not len(t["id"]):
        raise InputError(f"{path}: phantom CSV has no beads")
    xyz = np.stack([t["x"], t["y"], t["z"]], axis=1)
    check_finite(path, {"x": t["x"], "y": t["y"], "z": t["z"]}, lines=t["line"])
    diameter = t["diameter"]
    bad = ~np.isnan(diameter) & ~(np.isfinite(diameter) & (diameter > 0))
    if bad.any():
        i = int(np.argmax(bad))
        line = t["line"][i]
        raise InputError(f"{path}:{line}: diameter must be a positive number of mm (or empty); got {diameter[i]}")
    check_phantom_units(path, xyz, diameter)
    if not lattice and len(t["id"]) < MIN_PHANTOM_BEADS:
        raise InputError(f"{path}: a bead phantom needs at least {MIN_PHANTOM_BEADS} beads; got {len(t['id'])}")
    try:
        return Phantom(t["id"], xyz, t["diameter"], t["role"], lattice, pitch_mm)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from exc


def read_seeds(path: str | os.PathLike) -> dict:
    """Manual seeds ``id,x,y[,file[,frame]]`` (px): ``{(file name or "", frame): ((id, x, y), ...)}``.

    Rows without a file belong to the first frame of the sequence (key ``("", 0)``).

    Raises
    ------
    InputError
        Missing file or column, or a value that is not a number, naming the line.
    """
    t = read_table(path, SEEDS, lines=True)
    check_finite(path, {"x": t["x"], "y": t["y"]}, lines=t["line"])
    seeds: dict = {}
    for i, x, y, file, frame in zip(t["id"], t["x"], t["y"], t["file"], t["frame"]):
        key = (Path(file).name, int(frame)) if file else ("", 0)
        seeds.setdefault(key, []).append((float(int(i)), float(x), float(y)))
    return {k: tuple(v) for k, v in seeds.items()}


def check_finite(path, columns: dict[str, np.ndarray], *, lines=None) -> None:
    """Refuse NaN or infinite cells, naming the first one's line (``lines``: each row's, else row + 2) and column."""
    for name, values in columns.items():
        bad = ~np.isfinite(values)
        if bad.any():
            i = int(np.argmax(bad))
            line = i + 2 if lines is None else lines[i]
            raise InputError(f"{path}:{line}: column {name} must be a finite number; got {values[i]}")


def check_phantom_units(path, xyz_mm: np.ndarray, diameter_mm: np.ndarray) -> None:
    """Refuse bead coordinates whose size says they are in metres or inches, with the guess.

    Real phantoms span centimetres and hold beads millimetres apart and at least
    0.1 mm across. A phantom spanning under 1 mm, or with beads under 0.05 mm apart
    (median nearest neighbour) or under 0.1 mm across, was written in metres; beads
    0.05..1 mm apart, in inches; spanning over 2 m, in a smaller unit (micrometres?). A single bead is
    not judged.

    Raises
    ------
    InputError
        Naming the file, the extent or spacing found and the factor to apply.

    Examples
    --------
    >>> check_phantom_units("p.csv", np.array([[0, 0, 0], [10.0, 0, 0], [0, 10, 5]]), np.full(3, np.nan))
    >>> check_phantom_units("p.csv", np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0.005]]), np.full(3, np.nan))
    Traceback (most recent call last):
    ...
    fluorocal.stages.errors.InputError: p.csv: the phantom spans 0.01 mm, ... looks like metres; multiply ... 1000 ...
    """
    if len(xyz_mm) < 2:
        return
    from scipy.spatial import cKDTree

    extent = float(np.ptp(xyz_mm, axis=0).max())
    if not extent <= _MAX_PHANTOM_EXTENT_MM:  # before the k-d tree, which overflows on huge coordinates
        raise InputError(
            f"{path}: the phantom spans {extent:.3g} mm, more than any fluoroscope images "
            f"({_MAX_PHANTOM_EXTENT_MM:g} mm): looks like micrometres or another small unit "
            "(the phantom CSV is in mm)"
        )
    distance, _ = cKDTree(xyz_mm).query(xyz_mm, k=2)
    if not distance[:, 1].all():
        i = int(np.argmin(distance[:, 1]))
        i, j = np.flatnonzero(np.all(xyz_mm == xyz_mm[i], axis=1))[:2]
        raise InputError(f"{path}: lines {i + 2} and {j + 2} place two beads at the same point")
    spacing = float(np.median(distance[:, 1]))
    diameters = diameter_mm[np.isfinite(diameter_mm)]
    found = f"the phantom spans {extent:.3g} mm, beads {spacing:.3g} mm apart"
    if len(diameters) and float(np.median(diameters)) < _MIN_BEAD_DIAMETER_MM:
        found += f", {float(np.median(diameters)):.3g} mm across"
        guess = "metres", 1000
    elif extent < _MIN_PHANTOM_EXTENT_MM or spacing < 0.05:
        guess = "metres", 1000
    elif spacing < _MIN_PHANTOM_EXTENT_MM:
        guess = "inches", 25.4
    else:
        return
    raise InputError(
        f"{path}: {found}: looks like {guess[0]}; multiply the coordinates (and diameters) by {guess[1]:g} "
        "(the phantom CSV is in mm)"
    )
