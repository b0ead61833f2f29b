"""The artifact cache's data format: frozen dataclasses as JSON structure plus named numpy arrays.

An artifact is encoded into a JSON tree (``{"__dataclass__": name, "fields": ...}``,
``{"__array__": path}``, ``{"__tuple__": [...]}``, ``{"__dict__": {...}}`` and JSON
scalars) and a dict of numpy arrays. Decoding never imports anything and never calls
anything a manifest names: a dataclass name is looked up in an explicit registry of
the project's own artifact types (:func:`artifact_types`), built in code from the
stages' return annotations, the dataclass fields they declare and the classes listed
in :data:`ARTIFACT_CLASSES`. A name not in the registry is an :class:`UntrustedData` error,
which the cache turns into a miss.
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
import types as pytypes
import typing

import numpy as np

log = logging.getLogger(__name__)

#: the project's own artifact classes, module -> names: what the stages return, and the classes held in fields
#: their annotations leave untyped (``tuple``, ``object``). Other stages' (tests' toys) come from their annotations.
ARTIFACT_CLASSES = {
    "fluorocal.stages.detect": ("BeadCandidates",),
    "fluorocal.stages.centroid": ("Centroids",),
    "fluorocal.stages.label": ("Labels",),
    "fluorocal.stages.adjust": ("Adjustment",),
    "fluorocal.stages.field": ("CorrectionField", "PointwiseField"),
    "fluorocal.stages.learn.knn": ("KnnModel", "CvReport"),
    "fluorocal.stages.learn.grid": ("GridCvReport",),
    "fluorocal.stages.learn.result": ("IterationRecord", "LearnResult"),
    "fluorocal.stages.learn.uncertainty": ("JointUncertainty",),
    "fluorocal.stages.plate.result": ("PlateCalibration",),
}

_SCALARS = (bool, int, float, str, type(None))


class UntrustedData(ValueError):
    """A manifest's structure names a type outside the registry or is not what the encoder writes."""


def type_name(cls: type) -> str:
    """The registry name of an artifact class: ``module:qualname`` (a name, never imported)."""
    return f"{cls.__module__}:{cls.__qualname__}"


def artifact_types(stages=()) -> dict[str, type]:
    """Registry name -> class: ARTIFACT_CLASSES, the dataclasses the ``stages`` return, and those nested in them.

    Parameters
    ----------
    stages : iterable of Stage
        Stages whose functions' return annotations name their artifact classes.

    Returns
    -------
    dict of str to type

    Examples
    --------
    >>> from fluorocal.stages.learn import LearnResult
    >>> "fluorocal.stages.learn.result:LearnResult" in artifact_types()
    True
    >>> any(name.startswith("os:") for name in artifact_types())
    False
    """
    found: dict[str, type] = {}
    for stage in stages:
        _walk(_return_hint(stage.func), found)
    for module, names in ARTIFACT_CLASSES.items():
        mod = importlib.import_module(module)
        for name in names:
            _walk(getattr(mod, name), found)
    return found


def stage_kinds(stages) -> dict[str, type]:
    """Stage name -> the class its function returns (stages whose annotation names one class only)."""
    kinds = {}
    for stage in stages:
        hint = _return_hint(stage.func)
        args = typing.get_args(hint)
        if getattr(stage, "per_system", False) and typing.get_origin(hint) is tuple and args[1:] == (Ellipsis,):
            hint = args[0]  # a per-system stage returns its sequence; each frame's entry holds one element
        if isinstance(hint, type):
            kinds[stage.name] = hint
    return kinds


def _return_hint(func):
    try:
        return typing.get_type_hints(func).get("return")
    except Exception as exc:  # an unresolvable annotation: that stage's artifacts are not cached
        log.debug("return annotation of %s unresolvable (%s)", getattr(func, "__name__", func), exc)
        return None


def _walk(hint, found: dict[str, type]) -> None:
    if hint is None:
        return
    if typing.get_origin(hint) is not None or isinstance(hint, pytypes.UnionType):
        for arg in typing.get_args(hint):
            _walk(arg, found)
        return
    if not (isinstance(hint, type) and dataclasses.is_dataclass(hint)) or type_name(hint) in found:
        return
    found[type_name(hint)] = hint
    try:
        hints = typing.get_type_hints(hint)
    except Exception as exc:
        log.debug("field annotations of %s unresolvable (%s)", type_name(hint), exc)
        return
    for f in dataclasses.fields(hint):
        _walk(hints.get(f.name), found)


def encode(obj, arrays: dict, path: str, types: dict[str, type]):
    """The JSON tree of ``obj``; its arrays go into ``arrays`` under their field path.

    Raises
    ------
    TypeError
        For an object array, a dataclass not in ``types`` or a value of an unsupported type.
    """
    if isinstance(obj, np.ndarray):
        if obj.dtype == object:
            raise TypeError(f"artifact field {path} is an object array; use a typed array")
        arrays[path] = obj
        return {"__array__": path}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        name = type_name(type(obj))
        if types.get(name) is not type(obj):
            raise TypeError(
                f"artifact field {path} is a {name}, not a registered artifact type (annotate the stage's "
                "return type, or list the class in fluorocal.artifact_codec.ARTIFACT_CLASSES)"
            )
        fields = {
            f.name: encode(getattr(obj, f.name), arrays, f"{path}.{f.name}", types) for f in dataclasses.fields(obj)
        }
        return {"__dataclass__": name, "fields": fields}
    if isinstance(obj, (list, tuple)):
        return {"__tuple__": [encode(v, arrays, f"{path}.{i}", types) for i, v in enumerate(obj)]}
    if isinstance(obj, dict):
        return {"__dict__": {str(k): encode(v, arrays, f"{path}.{k}", types) for k, v in obj.items()}}
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, _SCALARS):
        return obj
    raise TypeError(f"artifact field {path} has unsupported type {type(obj).__name__}")


def decode(node, arrays: dict, types: dict[str, type]):
    """The artifact a tree from :func:`encode` describes, built only from classes in ``types``.

    Raises
    ------
    UntrustedData
        A type name not in ``types``, a missing array, a field the class does not
        have, or a structure :func:`encode` never writes.

    Examples
    --------
    >>> decode({"__dataclass__": "os:system", "fields": {}}, {}, {})
    Traceback (most recent call last):
    ...
    fluorocal.artifact_codec.UntrustedData: type 'os:system' is not a registered artifact type
    """
    if isinstance(node, _SCALARS):
        return node
    if not isinstance(node, dict):
        raise UntrustedData(f"unexpected {type(node).__name__} in an artifact tree")
    keys = set(node)
    if keys == {"__array__"}:
        if not isinstance(node["__array__"], str) or node["__array__"] not in arrays:
            raise UntrustedData(f"array {node['__array__']!r} is not in the entry")
        return arrays[node["__array__"]]
    if keys == {"__dataclass__", "fields"}:
        return _decode_dataclass(node, arrays, types)
    if keys == {"__tuple__"} and isinstance(node["__tuple__"], list):
        return tuple(decode(v, arrays, types) for v in node["__tuple__"])
    if keys == {"__dict__"} and isinstance(node["__dict__"], dict):
        return {k: decode(v, arrays, types) for k, v in node["__dict__"].items()}
    raise UntrustedData(f"unexpected node with keys {sorted(keys)} in an artifact tree")


def _decode_dataclass(node: dict, arrays: dict, types: dict[str, type]):
    name, values = node["__dataclass__"], node["fields"]
    cls = types.get(name) if isinstance(name, str) else None
    if cls is None:
        raise UntrustedData(f"type {name!r} is not a registered artifact type")
    if not isinstance(values, dict):
        raise UntrustedData(f"fields of {name} are not a mapping")
    allowed = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(values) - allowed)
    if unknown:
        raise UntrustedData(f"{name} has no field(s) {', '.join(unknown)}")
    try:
        return cls(**{k: decode(v, arrays, types) for k, v in values.items()})
    except UntrustedData:
        raise
    except Exception as exc:  # the class's own checks refused the values
        raise UntrustedData(f"{name} refused its stored fields ({exc})") from exc


def named_types(tree) -> set[str]:
    """Every dataclass name a tree mentions (for checking an entry without building it)."""
    out: set[str] = set()
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, dict):
            if isinstance(node.get("__dataclass__"), str):
                out.add(node["__dataclass__"])
            stack.extend(node.values())
        elif isinstance(node, list):
            stack.extend(node)
    return out
