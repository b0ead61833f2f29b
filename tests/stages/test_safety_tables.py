"""Phantom and table CSVs read as written (issue 28): ragged rows, roles, repeated columns, line numbers.

A row of five values under a four-column header was read with its columns shifted; ``MARKER`` was
accepted and then ignored (labelling looks for ``marker``); a bad cell after blank lines was reported
two lines early; a repeated ``x`` column was read as the later one.
"""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal.stages.errors import InputError
from fluorocal.stages.io import PHANTOM, read_phantom, read_seeds, read_table

CUBE = "".join(f"{i},{10 * (i & 1)},{10 * (i >> 1 & 1)},{10 * (i >> 2 & 1)}\n" for i in range(8))


def _csv(tmp_path, text):
    path = tmp_path / "phantom.csv"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    "row, n", [("8,5,5,5,7\n", 5), ("8,5,5\n", 3), ("8,5,5,5,\n", 5)], ids=["one more", "one fewer", "trailing comma"]
)
def test_a_row_with_more_or_fewer_values_than_the_header_is_refused_naming_its_line(tmp_path, row, n):
    path = _csv(tmp_path, "id,x,y,z\n" + CUBE + row)
    with pytest.raises(InputError, match=rf"phantom.csv:10: {n} values in a row under a header of 4 columns"):
        read_phantom(path)


@pytest.mark.parametrize("text", ["MARKER", "Marker", " marker "])
def test_roles_are_matched_in_any_case(tmp_path, text):
    rows = CUBE.splitlines()
    path = _csv(
        tmp_path, "id,x,y,z,diameter,role\n" + "".join(f"{r},2,{text if i < 2 else ''}\n" for i, r in enumerate(rows))
    )
    phantom = read_phantom(path)
    assert phantom.role.tolist() == ["marker", "marker"] + [""] * 6  # what labelling looks for


def test_an_unknown_role_is_refused_naming_its_line(tmp_path):
    rows = CUBE.splitlines()
    path = _csv(
        tmp_path, "id,x,y,z,role\n" + "".join(f"{r},{'fiducial' if i == 3 else ''}\n" for i, r in enumerate(rows))
    )
    with pytest.raises(InputError, match=r"phantom.csv:5: not 'marker' \(in any case\) or empty in column role"):
        read_phantom(path)


@pytest.mark.parametrize(
    "bad, message",
    [
        ("8,5,five,5", "not a number in column y: 'five'"),
        ("8,5,nan,5", "column y must be a finite number"),
        ("8,5,5,5,-1", "diameter must be a positive number"),
    ],
)
def test_errors_after_blank_lines_name_the_file_s_own_line(tmp_path, bad, message):
    header = "id,x,y,z,diameter\n" if bad.count(",") == 4 else "id,x,y,z\n"
    rows = CUBE if header == "id,x,y,z\n" else "".join(r + ",\n" for r in CUBE.splitlines())
    # line 1 header, lines 2-9 the cube, lines 10 and 11 blank, line 12 the bad row
    path = _csv(tmp_path, header + rows + "\n\n" + bad + "\n")
    with pytest.raises(InputError, match=rf"phantom.csv:12: {message}"):
        read_phantom(path)


def test_a_seed_after_blank_lines_is_named_by_its_line(tmp_path):
    path = tmp_path / "seeds.csv"
    path.write_text("id,x,y\n1,2,3\n\n\n2,inf,3\n")
    with pytest.raises(InputError, match=r"seeds.csv:5: column x must be a finite number"):
        read_seeds(path)


@pytest.mark.parametrize("header", ["id,x,x,y,z", "id,x,y,z,x"])
def test_a_column_named_twice_is_refused_as_such(tmp_path, header):
    path = _csv(tmp_path, header + "\n" + "".join(r + ",1\n" for r in CUBE.splitlines()))
    with pytest.raises(InputError, match=r"phantom.csv:1: column x appears twice in the header"):
        read_table(path, PHANTOM)


def test_a_column_under_its_name_and_its_older_name_is_refused(tmp_path):
    from fluorocal.stages.io import OBSERVATIONS

    path = tmp_path / "o.csv"
    path.write_text("file,id,x,y,sigma_x,sigma_y,rho,dx,delta_x\na,1,1,2,0.1,0.1,0,0.5,0.25\n")
    with pytest.raises(
        InputError, match=r"o.csv:1: column delta_x appears twice in the header \(as 'dx' and 'delta_x'\)"
    ):
        read_table(path, OBSERVATIONS)


def test_a_well_formed_phantom_reads_unchanged(tmp_path):
    path = _csv(tmp_path, "id,x,y,z\n" + CUBE)
    phantom = read_phantom(path)
    np.testing.assert_array_equal(phantom.xyz_mm[5], [10, 0, 10])  # bead 5 = 0b101: x and z at 10 mm
