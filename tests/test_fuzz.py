"""Fuzzing the readers of what a user hands over: only fluorocal's own errors may escape.

The config loader (random text, and a valid config with random values put under its keys),
every CSV reader (random bytes, and random cells under each schema's header) and the frame
readers (random bytes behind each format's suffix and signature) either return or raise a
:class:`~fluorocal.stages.errors.CalibError` subclass whose message is one line. Bounded and
derandomised, so CI stays fast and a failure reproduces; for a longer hunt set ``FUZZ_N=2000``
(examples per test) and ``FUZZ_RANDOM=1`` (new random examples each run).
"""

from __future__ import annotations

import itertools
import math
import os

import pytest
from fluorocal.config import load_config
from fluorocal.graph import stage_params_classes
from fluorocal.stages.errors import CalibError
from fluorocal.stages.io import TABLES, probe_frames, read_frames, read_phantom, read_seeds, read_table
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.pipeline.toy import make_project

FUZZ = settings(
    max_examples=int(os.environ.get("FUZZ_N", 50)),
    derandomize=not os.environ.get("FUZZ_RANDOM"),
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
_names = itertools.count()


def _only_own_errors(call) -> None:
    """Run ``call``; a CalibError with a one-line message is fine, anything else fails the test."""
    try:
        call()
    except CalibError as exc:
        assert "\n" not in str(exc), str(exc)


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz")
    make_project(root)
    return root


# --- the config loader ----------------------------------------------------------------------

_toml_scalars = st.one_of(
    st.integers(-(10**12), 10**12).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(
        lambda v: "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    ),
    st.booleans().map(lambda b: "true" if b else "false"),
    st.text(max_size=20).map(lambda s: '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'),
    st.sampled_from(['"frames/*.tif"', '"phantom.csv"', '"."', '"/"', '"frames"', '"*"', '""', "1979-05-27"]),
)
_toml_values = st.recursive(
    _toml_scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=3).map(lambda v: "[" + ", ".join(v) + "]"),
        st.dictionaries(st.sampled_from(["a", "file", "dir", "name"]), inner, max_size=2).map(
            lambda d: "{" + ", ".join(f"{k} = {v}" for k, v in d.items()) + "}"
        ),
    ),
    max_leaves=4,
)
_BASE = (
    '[phantom]\nfile = "phantom.csv"\n\n[[systems]]\nname = "A"\nframes = "frames/*.tif"\n'
    "source_image_distance = 1100\npixel_pitch = 0.25\n"
)
#: (table header or "" for the top level / the [[systems]] table above, key) pairs to put random values under
_KEYS = [("[[systems]]", k) for k in ("name", "frames", "source_image_distance", "pixel_pitch", "seeds", "bogus")] + [
    ("[phantom]", "lattice"),
    ("[phantom]", "pitch"),
    ("[calibration]", "scheme"),
    ("[output]", "dir"),
    ("[cache]", "dir"),
    ("[detect]", "min_diameter_px"),
    ("[detect]", "polarity"),
    ("[label]", "seeds"),
    ("[adjust]", "loss"),
    ("[learn]", "k"),
    ("", "systems"),
]


def _write_config(project, text: str | bytes):
    path = project / f"fuzz-{next(_names)}.toml"
    path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8", "surrogatepass"))
    return path


@FUZZ
@given(st.one_of(st.text(max_size=200), st.binary(max_size=200)))
def test_config_loader_random_text(project, text):
    path = _write_config(project, text)
    _only_own_errors(lambda: load_config(path, stage_params_allowed=stage_params_classes()))


@FUZZ
@given(st.lists(st.tuples(st.sampled_from(_KEYS), _toml_values), min_size=1, max_size=4))
def test_config_loader_random_values(project, edits):
    text = _BASE
    for (table, key), value in edits:
        if table == "[[systems]]":
            lines = [ln for ln in text.splitlines() if not ln.startswith(f"{key} =")]
            i = lines.index("[[systems]]")
            text = "\n".join(lines[: i + 1] + [f"{key} = {value}"] + lines[i + 1 :]) + "\n"
        elif table:
            text += f"\n{table}\n{key} = {value}\n"
        else:
            text = f"{key} = {value}\n" + text
    path = _write_config(project, text)
    _only_own_errors(lambda: load_config(path, stage_params_allowed=stage_params_classes()))


# --- the CSV readers -----------------------------------------------------------------------------

_cells = st.one_of(
    st.text(max_size=8),
    st.sampled_from(
        ["", "nan", "inf", "-1", "0", "1e308", "1e999", "3.5", "true", "a,b", '"', "\x00", "\ufeff", str(2**63)]
    ),
    st.integers(-(10**20), 10**20).map(str),
    st.floats().map(repr),
)
_READERS = [(t.name, lambda p, t=t: read_table(p, t)) for t in TABLES] + [
    ("phantom", read_phantom),
    ("seeds", read_seeds),
]


@FUZZ
@given(st.sampled_from(_READERS), st.one_of(st.binary(max_size=300), st.text(max_size=300)))
def test_csv_readers_random_content(tmp_path, reader, content):
    name, read = reader
    path = tmp_path / f"{name}-{next(_names)}.csv"
    path.write_bytes(content if isinstance(content, bytes) else content.encode("utf-8", "surrogatepass"))
    _only_own_errors(lambda: read(path))


@FUZZ
@given(st.sampled_from(_READERS), st.data())
def test_csv_readers_random_cells_under_each_schema(tmp_path, reader, data):
    name, read = reader
    table = next(t for t in TABLES if t.name == name)
    header = data.draw(st.lists(st.sampled_from(table.names + ["extra"]), min_size=1, unique=True))
    rows = data.draw(st.lists(st.lists(_cells, min_size=len(header), max_size=len(header)), max_size=5))
    text = "\n".join(",".join(r) for r in [header, *rows]) + "\n"
    path = tmp_path / f"{name}-{next(_names)}.csv"
    path.write_bytes(text.encode("utf-8", "surrogatepass"))
    _only_own_errors(lambda: read(path))


# --- the frame readers ---------------------------------------------------------------------------

_SIGNATURES = [b"", b"\x00" * 128 + b"DICM", b"II*\x00", b"MM\x00*", b"\x89PNG\r\n\x1a\n", b"RIFF\x00\x00\x00\x00AVI "]


@FUZZ
@given(
    st.sampled_from([".dcm", ".tif", ".png", ".avi", ".bin"]),
    st.sampled_from(_SIGNATURES),
    st.binary(max_size=400),
)
def test_frame_readers_random_bytes(tmp_path, suffix, signature, body):
    path = tmp_path / f"frame-{next(_names)}{suffix}"
    path.write_bytes(signature + body)
    _only_own_errors(lambda: probe_frames(path))
    _only_own_errors(lambda: read_frames(path))
