"""CSV schemas: one reader and one writer, errors naming file, line and column, exact float round trips."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fluorocal.stages.errors import InputError
from fluorocal.stages.io import (
    DETECTIONS,
    OBJECT_POINTS,
    OBSERVATIONS,
    PHANTOM,
    SEEDS,
    TABLES,
    Column,
    Table,
    read_seeds,
    read_table,
    write_csv,
    write_table,
)


def test_every_schema_names_its_columns_once():
    assert {t.name for t in TABLES} == {"phantom", "seeds", "detections", "observations", "object_points"}
    for t in TABLES:
        assert len(set(t.names)) == len(t.names) and all(c.dtype in (int, float, bool, str) for c in t.columns)
    with pytest.raises(InputError, match="repeat"):
        Table("bad", (Column("a"), Column("a")))


def test_observations_round_trip_exactly(tmp_path):
    rng = np.random.default_rng(5)
    n = 50
    columns = {
        "system": rng.choice(["A", "B"], n),
        "file": [f"f{k % 7}.dcm" for k in range(n)],
        "exposure": rng.integers(0, 9, n),
        "id": rng.integers(0, 10**8, n),
        **{c: rng.normal(0, 1, n) * 10.0 ** rng.integers(-12, 4, n) for c in ("x", "y", "sigma_x", "sigma_y", "rho")},
        "delta_x": rng.normal(0, 3, n),
        "inlier": rng.random(n) < 0.9,
    }
    columns["x"][:2] = [np.nextafter(512.0, 0.0), 1 / 3]
    write_table(tmp_path / "o.csv", OBSERVATIONS, columns)
    back = read_table(tmp_path / "o.csv", OBSERVATIONS)
    for name, values in columns.items():
        np.testing.assert_array_equal(back[name], np.asarray(values), err_msg=name)  # exact: floats as repr
    # absent optional columns: filled with their default, or left out when they have none
    assert np.all(back["frame"] == 0) and np.all(back["delta_y"] == 0.0) and "residual_x" not in back
    header = (tmp_path / "o.csv").read_text().splitlines()[0].split(",")
    assert header == [c for c in OBSERVATIONS.names if c in columns]  # the schema's order, whatever the mapping's


def test_object_points_keep_six_decimals(tmp_path):
    write_table(
        tmp_path / "p.csv", OBJECT_POINTS, {"id": [3], **{c: [1 / 3] for c in ("x", "y", "z", "sx", "sy", "sz")}}
    )
    write_csv(tmp_path / "q.csv", OBJECT_POINTS.names, [[3, *[1 / 3] * 6]])  # the schema-less writer of before
    assert (tmp_path / "p.csv").read_bytes() == (tmp_path / "q.csv").read_bytes()
    assert (tmp_path / "p.csv").read_text().splitlines()[1] == "3," + ",".join(["0.333333"] * 6)


def test_older_header_names_are_read(tmp_path):
    p = tmp_path / "o.csv"
    p.write_text("file,frame,id,x,y,sigma_x,sigma_y,rho,dx,dy,rx\na.tif,2,5,1,2,0.1,0.1,0,0.25,-0.5,0.01\n")
    t = read_table(p, OBSERVATIONS)
    assert (t["delta_x"][0], t["delta_y"][0], t["residual_x"][0], t["system"][0]) == (0.25, -0.5, 0.01, "A")


@pytest.mark.parametrize(
    "text, message",
    [
        ("file,frame,x,y\n", r"d.csv: detections CSV needs columns file,frame,x,y,sigma_x.*; missing sigma_x,"),
        (
            "file,frame,x,y,sigma_x,sigma_y,rho,major,minor\na,0,1,2,3,4,5,6\n",
            r"d.csv:2: 8 values in a row under a header of 9 columns",
        ),
        (
            "file,frame,x,y,sigma_x,sigma_y,rho,major,minor\na,0,1,2,3,4,5,6,7\na,1.5,1,2,3,4,5,6,7\n",
            r"d.csv:3: not an integer in column frame: '1.5'",
        ),
        (
            "file,frame,x,y,sigma_x,sigma_y,rho,major,minor\na,0,1,two,3,4,5,6,7\n",
            r"d.csv:2: not a number in column y: 'two'",
        ),
    ],
)
def test_errors_name_file_line_and_column(tmp_path, text, message):
    (tmp_path / "d.csv").write_text(text)
    with pytest.raises(InputError, match=message):
        read_table(tmp_path / "d.csv", DETECTIONS)


def test_missing_file_and_bad_columns_on_writing(tmp_path):
    with pytest.raises(InputError, match="nope.csv: seeds file not found"):
        read_table(tmp_path / "nope.csv", SEEDS)
    with pytest.raises(InputError, match="unknown column.*colour; missing y"):
        write_table(tmp_path / "s.csv", SEEDS, {"id": [1], "x": [0.0], "colour": ["red"]})
    with pytest.raises(InputError, match="differ in length"):
        write_table(tmp_path / "s.csv", SEEDS, {"id": [1, 2], "x": [0.0], "y": [1.0]})
    assert not (tmp_path / "s.csv").exists()


def test_detections_defaults_and_booleans(tmp_path):
    p = tmp_path / "d.csv"
    p.write_text("file,frame,x,y,sigma_x,sigma_y,rho,major,minor,ok\na,0,1,2,3,4,5,6,7,\na,0,1,2,3,4,5,6,7,no\n")
    t = read_table(p, DETECTIONS)
    assert t["ok"].tolist() == [True, False] and all(math.isnan(v) for v in t["score"])


def test_phantom_and_seeds_readers(tmp_path):
    p = tmp_path / "p.csv"
    p.write_text("id,x,y,z\n1,0,0,0\n")
    t = read_table(p, PHANTOM)
    assert np.isnan(t["diameter"][0]) and t["role"][0] == ""
    s = tmp_path / "s.csv"
    s.write_text("id,x,y,file,frame\n4,1.5,2.5,,\n5,3,4,dir/a.dcm,2\n")
    assert read_seeds(s) == {("", 0): ((4.0, 1.5, 2.5),), ("a.dcm", 2): ((5.0, 3.0, 4.0),)}


def test_csv_text_is_what_the_csv_module_writes_cell_by_cell():
    """Rows of plain ints and floats (one format per row layout) and the rest: the text of the documented rule."""
    import csv
    import io

    from fluorocal.stages.io import csv_text

    rows = [
        [1, 0.5, -2.25],
        [-7, float("nan"), float("inf")],
        [0, -0.0, 1e300],
        [3, 1e-9, 123456.7890125],
        [True, np.float32(0.1), np.int64(5)],  # not plain: bool, numpy scalars
        [False, 7, 0.5],  # a bool among plain cells: "False", not "0"
        ["a,b", 'say "hi"', "line\nbreak"],  # quoted as csv quotes them
        [],
        [2, 0.25, -1.0],
    ]
    expected = io.StringIO()
    writer = csv.writer(expected)
    writer.writerow(["id", "x", "y"])
    for row in rows:
        writer.writerow([f"{v:.6f}" if isinstance(v, (float, np.floating)) else str(v) for v in row])
    assert csv_text(["id", "x", "y"], iter(rows)) == expected.getvalue()


def test_csv_text_rows_may_be_any_iterable_as_for_the_csv_module():
    """A row given as an iterator or generator is written whole, not as an empty line (or a format error)."""
    from fluorocal.stages.io import csv_text

    rows = [iter([1, 0.5]), (str(v) for v in ["a", "b,c"]), iter([])]
    assert csv_text(["id", "x"], rows) == 'id,x\r\n1,0.500000\r\na,"b,c"\r\n\r\n'
