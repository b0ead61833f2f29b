"""Project configuration: TOML validated into frozen dataclasses.

Every error names the file and the key, and says what was expected, e.g.
``proj.toml: [[systems]] #1 "A": key 'pixel_pitch': expected a number (mm); got "0.25mm"``.
Paths in the file are relative to the config file.
"""

from __future__ import annotations

import dataclasses
import enum
import glob
import math
import os
import re
import stat
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path

from fluorocal.compute import ComputeConfig, compute_from_table
from fluorocal.config_schema import DEFAULT_SCHEME, SCHEMA, schema_default, schema_keys
from fluorocal.outputs import safe_name
from fluorocal.stages.errors import InputError
from fluorocal.stages.orientation import ANGLE_TOL_DEG, check_angle

if typing.TYPE_CHECKING:  # imported when a configuration is made: `fluorocal --help` imports no learning
    from fluorocal.stages.kinds import PhantomKind
    from fluorocal.stages.learn.params import Scheme


class ConfigError(InputError):
    """The project configuration is invalid; the message names the key."""


#: stage-section keys that another setting owns: (section, key) -> the owner, named in the refusal
OWNED_ELSEWHERE = {
    ("adjust", "estimate_iop"): "[calibration] scheme (the knn+iop schemes estimate the IOP in the adjustment)",
    ("adjust", "additional_parameters"): "[calibration] scheme (polynomial estimates them)",
    ("adjust", "fixed_additional_parameters"): "[learn] polynomial_fixed (the polynomial scheme's held terms)",
    ("adjust", "compute_covariance"): "[learn] fast_intermediate (the loop decides which solves compute it)",
    ("learn", "smooth"): "[calibration] scheme (knn+smooth and knn+iop+smooth smooth the kNN field)",
    ("label", "source_image_distance_mm"): "[[systems]] source_image_distance",
    ("label", "pixel_pitch_mm"): "[[systems]] pixel_pitch",
    ("label", "image_size_px"): "the frames themselves",
    ("label", "seeds"): "[[systems]] seeds",
}


#: largest integer a stage's parameter may be (a C int: OpenCV and numpy take them as such)
MAX_CONFIG_INT = 2**31 - 1
#: largest magnitude of a stage's float parameter (beyond any px, mm or ratio; inf and 1e400 refused)
MAX_CONFIG_FLOAT = 1e15


def _reject_owned(section: str, table: dict, path: Path) -> None:
    for key in table:
        if (section, key) in OWNED_ELSEWHERE:
            owner = OWNED_ELSEWHERE[(section, key)]
            raise ConfigError(f"{_where(path, f'[{section}] ', key)}: set by {owner}; remove it from [{section}]")


@dataclass(frozen=True)
class PhantomConfig:
    """The ``[phantom]`` table: a phantom file, or a grid plate's lattice and pitch; and the kind it names.

    ``kind`` (:class:`~fluorocal.stages.kinds.PhantomKind`) is looked up once, from the table's spelling
    (:data:`fluorocal.stages.kinds.KINDS`); what differs between kinds is asked of it.
    """

    file: Path | None = None
    lattice: str = ""
    pitch_mm: float = 0.0
    kind: PhantomKind = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        from fluorocal.stages.kinds import phantom_kind

        object.__setattr__(self, "kind", phantom_kind(self.lattice))


@dataclass(frozen=True)
class OrientationConfig:
    """A group of a system's frames taken at one C-arm orientation (``orientations`` in ``[[systems]]``).

    ``frames`` are the system's own paths (as in :attr:`SystemConfig.frames`); ``orbit_deg`` and
    ``tilt_deg`` are the C-arm's angles in degrees, both or neither given.
    """

    name: str
    frames: tuple[Path, ...]
    orbit_deg: float | None = None
    tilt_deg: float | None = None


@dataclass(frozen=True)
class SystemConfig:
    name: str
    frames: tuple[Path, ...]
    source_image_distance_mm: float
    pixel_pitch_mm: float
    seeds: Path | None = None
    #: the frames grouped by C-arm orientation; empty: each frame is its own (fluorocal.orientations)
    orientations: tuple[OrientationConfig, ...] = ()


@dataclass(frozen=True)
class Config:
    """A validated project configuration.

    ``stage_params`` maps a stage name to the raw table of its section
    (``[detect]``, ``[centroid]``, ...); it is turned into the stage's
    ``Params`` by :func:`params_from_dict` when the stage graph is built.
    """

    path: Path
    phantom: PhantomConfig
    systems: tuple[SystemConfig, ...]
    scheme: Scheme = DEFAULT_SCHEME
    output_dir: Path = Path("out")
    cache_dir: Path = Path(".fluorocal")
    stage_params: dict = field(default_factory=dict)
    compute: ComputeConfig = ComputeConfig()

    def __post_init__(self):
        from fluorocal.stages.learn.params import Scheme

        object.__setattr__(self, "scheme", Scheme.parse(self.scheme, where="Config.scheme"))

    @property
    def root(self) -> Path:
        return self.path.parent


#: plausible ranges of the [[systems]] numbers, mm: (key, low, high); outside them a unit or typing slip is likelier
SYSTEM_RANGES_MM = (("source_image_distance", 100.0, 5000.0), ("pixel_pitch", 0.01, 5.0))


def _where(path: Path, section: str, key: str) -> str:
    return f"{path.name}: {section}key '{key}'"


def _as_float(value: int | float) -> float:
    """``value`` as a float; an integer beyond a float's range (TOML allows 10**400) as infinity, refused as such."""
    try:
        return float(value)
    except OverflowError:
        return math.inf if value > 0 else -math.inf


def _expect(value, kind, what: str, path: Path, section: str, key: str):
    ok = isinstance(value, kind) and not (kind in ((int, float), float) and isinstance(value, bool))
    if not ok:
        raise ConfigError(f"{_where(path, section, key)}: expected {what}; got {value!r}")
    if isinstance(value, str) and "\x00" in value:  # no file name or name holds one; the OS refuses it mid-run
        raise ConfigError(f"{_where(path, section, key)}: expected {what}; got {value!r} with a NUL character")
    return value


def _reject_unknown(table: dict, allowed: set[str], path: Path, section: str) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise ConfigError(
            f"{_where(path, section, unknown[0])}: unknown key; allowed keys are {', '.join(sorted(allowed))}"
        )


def _resolve_frames(value, root: Path, path: Path, section: str) -> tuple[Path, ...]:
    if isinstance(value, str):
        # the pattern is the user's, the project's own path is not: `scan[1]/` must not match `scan1/`
        pattern = value if os.path.isabs(value) else os.path.join(glob.escape(str(root)), value)
        matches = sorted(glob.glob(pattern))
        if not matches:
            raise ConfigError(f"{_where(path, section, 'frames')}: no file matches {value!r} (relative to {root})")
        folders = [m for m in matches if os.path.isdir(m)]
        if folders:
            raise ConfigError(
                f"{_where(path, section, 'frames')}: {value!r} matches the folder {folders[0]}; "
                "use a pattern that matches frame files only (e.g. frames/*.dcm)"
            )
        _check_regular(matches, path, section)
        return tuple(Path(m) for m in matches)
    if isinstance(value, list) and value and all(isinstance(v, str) for v in value):
        files = tuple(root / v for v in value)
        _check_regular(files, path, section)
        for f in files:
            if f.is_dir():
                raise ConfigError(f"{_where(path, section, 'frames')}: {f} is a folder; list frame files")
            if not f.is_file():
                raise ConfigError(f"{_where(path, section, 'frames')}: file not found: {f}")
        return files
    raise ConfigError(
        f"{_where(path, section, 'frames')}: expected a glob string or a non-empty list of files; got {value!r}"
    )


def _check_own_frames(systems, path: Path) -> None:
    """Refuse two systems listing one frame file: one detector's frames are not the other's (else: learn fails)."""
    if len(systems) < 2:
        return
    first = {f.resolve(): f for f in systems[0].frames}
    shared = [f for f in systems[1].frames if f.resolve() in first]
    if shared:
        more = f" and {len(shared) - 1} more" if len(shared) > 1 else ""
        raise ConfigError(
            f"{path.name}: [[systems]] #2 key 'frames': system {systems[1].name} lists {shared[0]}{more}, "
            f"a frame of system {systems[0].name}; give each system its own detector's frames"
        )


def _check_regular(files, path: Path, section: str) -> None:
    """Refuse a frame that is a device or a pipe (``/dev/zero`` is read, and hashed, forever)."""
    for f in files:
        if os.path.exists(f) and not os.path.isdir(f) and not stat.S_ISREG(os.stat(f).st_mode):  # folders: below
            raise ConfigError(f"{_where(path, section, 'frames')}: {f} is not a regular file; list frame files")


def _phantom(table: dict, root: Path, path: Path) -> PhantomConfig:
    section = "[phantom] "
    _expect(table, dict, "a table [phantom]", path, "", "phantom")
    _reject_unknown(table, schema_keys("phantom"), path, section)
    if "file" in table:
        f = root / _expect(table["file"], str, "a file name", path, section, "file")
        if not f.is_file():
            raise ConfigError(f"{_where(path, section, 'file')}: phantom file not found: {f}")
        _check_phantom_file(f, path)
        if "lattice" not in table:
            return PhantomConfig(file=f)
    else:
        f = None
    from fluorocal.stages.kinds import LATTICE_SPELLINGS

    shown = " or ".join(f'"{spelling}"' for spelling in LATTICE_SPELLINGS)
    lattice = _expect(table.get("lattice"), str, f'a phantom "file", or "lattice" = {shown}', path, section, "lattice")
    if lattice not in LATTICE_SPELLINGS:
        raise ConfigError(f"{_where(path, section, 'lattice')}: expected {shown}; got {lattice!r}")
    pitch = _as_float(_expect(table.get("pitch"), (int, float), "a positive number (mm)", path, section, "pitch"))
    if not (math.isfinite(pitch) and pitch > 0):
        raise ConfigError(f"{_where(path, section, 'pitch')}: expected a positive number (mm); got {pitch}")
    if pitch < 1.0:  # grid plates' pitches are millimetres; a smaller number is a unit slip
        guess = "metres: multiply by 1000" if pitch < 0.05 else "inches: multiply by 25.4"
        raise ConfigError(f"{_where(path, section, 'pitch')}: {pitch:g} mm looks like {guess} (pitch is in mm)")
    return PhantomConfig(file=f, lattice=lattice, pitch_mm=pitch)


def _check_phantom_file(file: Path, path: Path) -> None:
    """Read the phantom once at load, so a bad file is refused before any stage runs."""
    from fluorocal.stages.io import read_phantom

    try:
        read_phantom(file)
    except InputError as exc:
        raise ConfigError(f"{_where(path, '[phantom] ', 'file')}: {exc}") from exc


def _system(table: dict, i: int, root: Path, path: Path) -> SystemConfig:
    section = f"[[systems]] #{i + 1} "
    _expect(table, dict, "a [[systems]] table", path, "", "systems")
    _reject_unknown(table, schema_keys("systems"), path, section)
    name = _expect(table.get("name"), str, 'a name such as "A"', path, section, "name")
    if not name.strip():
        raise ConfigError(f'{_where(path, section, "name")}: expected a non-empty name such as "A"; got {name!r}')
    numbers = {}
    for key, low, high in SYSTEM_RANGES_MM:
        expected = f"a positive number (mm) in {low:g}..{high:g} mm"
        v = _as_float(_expect(table.get(key), (int, float), expected, path, section, key))
        if not (math.isfinite(v) and low <= v <= high):
            raise ConfigError(f"{_where(path, section, key)}: expected {expected}; got {v:g}")
        numbers[key] = v
    frames = _resolve_frames(table.get("frames"), root, path, section)
    seeds = None
    if "seeds" in table:
        seeds = root / _expect(table["seeds"], str, "a CSV file of id,x,y[,file,frame] seeds", path, section, "seeds")
        if not seeds.is_file():
            raise ConfigError(f"{_where(path, section, 'seeds')}: seeds file not found: {seeds}")
    orientations = _orientations(table.get("orientations"), frames, root, path, section)
    return SystemConfig(name, frames, numbers["source_image_distance"], numbers["pixel_pitch"], seeds, orientations)


def _orientations(value, frames: tuple[Path, ...], root: Path, path: Path, section: str):
    """The ``orientations`` of a ``[[systems]]`` table: every frame of the system in exactly one group."""
    if value is None:
        return ()
    if not isinstance(value, list) or not value:
        raise ConfigError(
            f"{_where(path, section, 'orientations')}: expected a list of tables "
            f'[{{name = "orbit30", frames = ["a.dcm"], orbit = 30, tilt = 0}}, ...]; got {value!r}'
        )
    own = {f.resolve(): f for f in frames}  # the system's frames, by where they are
    group_of: dict[Path, str] = {}
    groups = []
    for i, table in enumerate(value):
        where = f"{section}orientations #{i + 1} "
        group = _orientation(table, own, root, path, where)
        if any(g.name == group.name for g in groups):
            raise ConfigError(
                f"{_where(path, where, 'name')}: {group.name!r} names two orientations; names must differ"
            )
        for f in group.frames:
            if f in group_of:
                raise ConfigError(
                    f"{_where(path, where, 'frames')}: {f.name} is already in orientation {group_of[f]!r}; "
                    "a frame belongs to one orientation"
                )
            group_of[f] = group.name
        twin = next((g for g in groups if _same_angles(g, group)), None)
        if twin is not None:
            raise ConfigError(
                f"{_where(path, where, 'orbit')}: orientations {twin.name!r} and {group.name!r} have the same "
                "angles; make them one orientation"
            )
        groups.append(group)
    missing = [f for f in frames if f not in group_of]
    if missing:
        raise ConfigError(
            f"{_where(path, section, 'orientations')}: frame {missing[0].name} is in no orientation "
            f"({len(missing)} frame(s) are not); when orientations are given, each frame must be in one"
        )
    return tuple(groups)


def _same_angles(a: OrientationConfig, b: OrientationConfig) -> bool:
    if a.orbit_deg is None or b.orbit_deg is None:
        return False
    return math.hypot(a.orbit_deg - b.orbit_deg, a.tilt_deg - b.tilt_deg) <= ANGLE_TOL_DEG


def _orientation(table, own: dict, root: Path, path: Path, where: str) -> OrientationConfig:
    """One group of ``orientations``: its name, its frames (each one of the system's) and its angles."""
    _expect(table, dict, 'a table {name = "...", frames = [...], orbit = ..., tilt = ...}', path, where, "orientations")
    _reject_unknown(table, schema_keys("systems.orientations"), path, where)
    name = _expect(table.get("name"), str, 'a name such as "orbit30"', path, where, "name")
    try:
        safe_name(name, what="orientation name")  # names become file names (field_<system>_<name>.npz)
    except InputError as exc:
        raise ConfigError(f"{_where(path, where, 'name')}: {exc}") from None
    frames = []
    for f in _resolve_frames(table.get("frames"), root, path, where):
        if f.resolve() not in own:
            raise ConfigError(f"{_where(path, where, 'frames')}: {f} is not one of the system's frames")
        frames.append(own[f.resolve()])
    if ("orbit" in table) != ("tilt" in table):
        given = "orbit" if "orbit" in table else "tilt"
        raise ConfigError(f"{_where(path, where, given)}: give both orbit and tilt (degrees), or neither")
    angles = []
    for key in ("orbit", "tilt"):
        if key in table:
            try:
                angles.append(check_angle(table[key], key))
            except InputError as exc:
                raise ConfigError(f"{_where(path, where, key)}: {exc}") from None
    return OrientationConfig(name, tuple(dict.fromkeys(frames)), *angles)


def read_text(path: Path) -> str:
    """A config file's text: UTF-8 (a byte-order mark is allowed).

    Raises
    ------
    ConfigError
        The file cannot be read or is not UTF-8 text.
    """
    try:
        return path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{path.name}: not UTF-8 text (byte {exc.object[exc.start]:#04x} at offset {exc.start}); save it as UTF-8"
        ) from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror or exc})") from None


def check_writable_dir(folder: Path, *, where: str) -> None:
    """Refuse a folder fluorocal must write into that is a file, or that cannot be created or written.

    The folder need not exist: then its nearest existing parent must be a writable folder.
    Called at load, so the refusal comes before any stage runs.

    Raises
    ------
    ConfigError
        Naming ``where`` (the file and key), the path and what to do.

    Examples
    --------
    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     check_writable_dir(Path(d) / "out" / "sub", where="p.toml: [output] key 'dir'")
    """
    folder = Path(folder)
    probe = folder
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    if not probe.is_dir():
        raise ConfigError(f"{where}: {probe} is a file, not a folder; remove it or choose another folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise ConfigError(f"{where}: {probe} is not writable; fix its permissions or choose another folder")


def _parse_toml(path: Path) -> dict:
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    try:
        return tomllib.loads(read_text(path))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path.name}: not valid TOML ({exc})") from exc
    except RecursionError:
        raise ConfigError(f"{path.name}: not a project file (arrays or tables nested too deeply)") from None
    except ValueError:  # an integer past Python's digit limit (4300), which tomllib does not name
        key = re.search(r"([\w.\"'-]+)\s*=\s*[+-]?[0-9_]{1000,}", read_text(path))
        where = f"key {key.group(1)!r}" if key else "an integer"
        raise ConfigError(f"{path.name}: {where}: a number of thousands of digits; give a number in range") from None


def load_config(
    path: str | Path, *, stage_params_allowed: dict[str, type] | None = None, writable: bool = True
) -> Config:
    """Read and validate a project TOML file.

    Parameters
    ----------
    path : str or Path
    stage_params_allowed : dict of str to dataclass type, optional
        Stage sections allowed in the file (``[detect]`` ...) and their
        ``Params`` classes, used to reject unknown keys early.
    writable : bool
        Check that the output and cache folders can be written (``inspect`` only reads them).

    Raises
    ------
    ConfigError
        Missing file, TOML syntax error, unknown key, wrong type or value; the
        message names the file and key.
    """
    path = Path(path).resolve()
    data = _parse_toml(path)
    stage_params_allowed = stage_params_allowed or {}
    _reject_unknown(data, {k.section for k in SCHEMA if "." not in k.section} | set(stage_params_allowed), path, "")
    root = path.parent
    if "phantom" not in data:
        raise ConfigError(f"{path.name}: key 'phantom': missing; add a [phantom] table with file = \"phantom.csv\"")
    phantom = _phantom(data["phantom"], root, path)
    systems_raw = data.get("systems")
    if not isinstance(systems_raw, list) or not 1 <= len(systems_raw) <= 2:
        raise ConfigError(f"{path.name}: key 'systems': expected one or two [[systems]] tables; got {systems_raw!r}")
    systems = tuple(_system(t, i, root, path) for i, t in enumerate(systems_raw))
    for i, system in enumerate(systems):  # names become file names (field_<name>.npz)
        safe_name(system.name, what=f"{path.name}: [[systems]] #{i + 1} key 'name': system name")
    names = [s.name for s in systems]
    if len(set(names)) != len(names):
        raise ConfigError(f"{path.name}: [[systems]] key 'name': names must differ; got {names}")
    _check_own_frames(systems, path)

    scheme = _scheme(data, path, phantom)

    output = _expect(data.get("output", {}), dict, "a table [output]", path, "", "output")
    _reject_unknown(output, schema_keys("output"), path, "[output] ")
    out_dir = root / _expect(
        output.get("dir", schema_default("output", "dir")), str, "a directory name", path, "[output] ", "dir"
    )
    cache = _expect(data.get("cache", {}), dict, "a table [cache]", path, "", "cache")
    _reject_unknown(cache, schema_keys("cache"), path, "[cache] ")
    cache_dir = root / _expect(
        cache.get("dir", schema_default("cache", "dir")), str, "a directory name", path, "[cache] ", "dir"
    )
    for section, folder in (("[output] ", out_dir), ("[cache] ", cache_dir)) if writable else ():
        check_writable_dir(folder, where=_where(path, section, "dir"))

    try:
        compute = compute_from_table(data.get("compute", {}), path.name)
    except InputError as exc:
        raise ConfigError(str(exc)) from None

    stage_params = {}
    for stage, cls in stage_params_allowed.items():
        if stage in data:
            table = _expect(data[stage], dict, f"a table [{stage}]", path, "", stage)
            _reject_owned(stage, table, path)
            params_from_dict(cls, table, where=f"{path.name}: [{stage}] ")
            stage_params[stage] = table
    return Config(path, phantom, systems, scheme, out_dir, cache_dir, stage_params, compute)


def _scheme(data: dict, path: Path, phantom):
    """``[calibration] scheme``, parsed once (:class:`~fluorocal.stages.learn.params.Scheme`), for this phantom."""
    calibration = _expect(data.get("calibration", {}), dict, "a table [calibration]", path, "", "calibration")
    _reject_unknown(calibration, schema_keys("calibration"), path, "[calibration] ")
    from fluorocal.stages.learn.params import Scheme

    where = _where(path, "[calibration] ", "scheme")
    try:
        scheme = Scheme.parse(calibration.get("scheme", schema_default("calibration", "scheme")), where=where)
    except InputError as exc:
        raise ConfigError(str(exc)) from None
    if scheme not in phantom.kind.schemes:
        kind = phantom.kind
        raise ConfigError(
            f"{where}: {kind.noun} is calibrated {kind.calibrated_by}; expected one of {', '.join(kind.schemes)} "
            f"(none: no correction); got {str(scheme)!r}"
        )
    return scheme


def params_from_dict(cls, table: dict, *, where: str = ""):
    """Build a frozen ``Params`` dataclass from a dict, rejecting unknown keys and wrong types.

    ``cls`` may be a tuple of dataclasses whose fields do not overlap (a section that
    holds several of them, as ``[adjust]`` holds the solver options and the data
    selection): the keys are split by field name and a tuple of instances is returned.

    Examples
    --------
    >>> @dataclass(frozen=True)
    ... class P:
    ...     radius_px: float = 3.0
    >>> params_from_dict(P, {"radius_px": 4})
    P(radius_px=4.0)
    >>> @dataclass(frozen=True)
    ... class Q:
    ...     n: int = 1
    >>> params_from_dict((P, Q), {"n": 2})
    (P(radius_px=3.0), Q(n=2))
    """
    classes = cls if isinstance(cls, tuple) else (cls,)
    owner = {f.name: c for c in classes for f in dataclasses.fields(c)}
    values: dict[type, dict] = {c: {} for c in classes}
    for key, value in table.items():
        if key not in owner:
            raise ConfigError(f"{where}key '{key}': unknown; allowed keys are {', '.join(sorted(owner))}")
        values[owner[key]][key] = _coerce(value, typing.get_type_hints(owner[key])[key], f"{where}key '{key}'")
    try:
        built = tuple(c(**values[c]) for c in classes)
    except (TypeError, ValueError) as exc:  # a Params class's own checks (InputError is a ValueError)
        raise ConfigError(f"{where.rstrip()} {exc}".strip()) from exc
    return built if isinstance(cls, tuple) else built[0]


def _int_in_range(value: int, where: str) -> int:
    """``value`` if it fits a C int (what the libraries take); counts (``n_*``) and seeds also not negative."""
    lowest = 0 if re.search(r"key '(n_\w+|\w*seed)'", where) else -MAX_CONFIG_INT
    if not lowest <= value <= MAX_CONFIG_INT:
        shown = str(value) if len(str(value)) <= 30 else f"{str(value)[:12]}... ({len(str(value))} digits)"
        raise ConfigError(f"{where}: expected an integer in {lowest}..{MAX_CONFIG_INT}; got {shown}")
    return value


def _coerce(value, hint, where: str):
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        options = [o for o in typing.get_args(hint) if o is not type(None)]
        if value is not None and len(options) == 1:  # an optional value given: its own type's message
            return _coerce(value, options[0], where)
        for option in typing.get_args(hint):
            try:
                return _coerce(value, option, where)
            except ConfigError:
                continue
        raise ConfigError(f"{where}: expected {hint}; got {value!r}")
    if hint is type(None):
        if value is None:
            return None
        raise ConfigError(f"{where}: expected nothing; got {value!r}")
    if hint is bool:
        if isinstance(value, bool):
            return value
    elif hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return _int_in_range(value, where)
    elif hint is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            number = _as_float(value)
            if not math.isfinite(number) or abs(number) > MAX_CONFIG_FLOAT:
                shown = value if abs(number) < math.inf else "an integer beyond a float's range"
                raise ConfigError(f"{where}: expected a finite number of size up to {MAX_CONFIG_FLOAT:g}; got {shown}")
            return number
    elif hint is str:
        if isinstance(value, str):
            return value
    elif isinstance(hint, type) and issubclass(hint, enum.Enum):
        if isinstance(value, str) and value in hint._value2member_map_:
            return hint(value)
        raise ConfigError(f"{where}: expected one of {', '.join(repr(m.value) for m in hint)}; got {value!r}")
    elif origin is tuple:
        if isinstance(value, list):
            args = typing.get_args(hint)
            inner = args[0] if args else object
            return tuple(
                _coerce(v, inner, where) if inner is not object and inner is not Ellipsis else v for v in value
            )
    elif hint is object or hint is typing.Any:
        return value
    raise ConfigError(f"{where}: expected {getattr(hint, '__name__', hint)}; got {value!r}")
