"""Bad input: one clear line naming the file or key and what to do, exit 2, nothing half-written, no traceback.

Each test is one row of the README's table of what was tried and what happens. Refusals that
guard against a silent wrong calibration (frames paired with the wrong partner, a phantom in
metres) come first.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import OpenImageIO as oiio
import pytest
from fluorocal.cli import main
from fluorocal.config import ConfigError, load_config
from fluorocal.stages.errors import InputError
from fluorocal.stages.io import atomic, read_phantom, tables, write_still
from fluorocal.units import MIN_FRAME_PX, frame_units

from tests.pipeline.toy import make_project, make_two_system_project


def _cli(argv, capsys) -> tuple[int, str]:
    """Exit code and stderr of ``fluorocal ARGV``; stderr must be one line without a traceback."""
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err
    assert len(err.splitlines()) == 1, err
    return rc, err


def _write_multipage_tiff(path, n_pages: int, value: int = 100) -> None:
    spec = oiio.ImageSpec(10, 8, 1, "uint16")
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), [spec] * n_pages)
    for i in range(n_pages):
        if i:
            assert out.open(str(path), spec, "appendsubimage")
        assert out.write_image(np.full((8, 10, 1), value * (i + 1), np.uint16))
    out.close()


# --- silent wrong calibrations ---------------------------------------------------------------


def test_biplanar_frame_missing_on_one_side_is_refused(tmp_path, capsys):
    cfg = make_two_system_project(tmp_path)
    (tmp_path / "frames" / "B" / "f1.tif").unlink()
    rc, err = _cli(["run", cfg], capsys)
    assert rc == 2
    assert "same number of frames" in err and "A: 3, B: 2" in err
    assert "f2.tif has no partner in system B" in err  # A's third frame: the one left without a partner
    assert not (tmp_path / "out").exists() and not (tmp_path / ".fluorocal").exists()


def test_multipage_tiff_counts_frames_not_files(tmp_path):
    cfg = make_two_system_project(tmp_path)
    (tmp_path / "frames" / "B" / "f0.tif").unlink()
    _write_multipage_tiff(tmp_path / "frames" / "B" / "f0.tif", 2)  # B: 2 + 1 + 1 = 4 frames, A: 3
    with pytest.raises(InputError, match=r"A: 3, B: 4 \(f0.tif holds 2 frames\).*f2.tif has no partner in system A"):
        frame_units(load_config(cfg))


def test_equal_frame_counts_pair_across_multipage_files(tmp_path):
    cfg = make_two_system_project(tmp_path)
    for name in ("f0.tif", "f1.tif"):
        (tmp_path / "frames" / "B" / name).unlink()
    _write_multipage_tiff(tmp_path / "frames" / "B" / "f0.tif", 2)  # B: 2 + 1 = 3 frames, as A
    units = frame_units(load_config(cfg))
    assert [u.exposure for u in units if u.system == 1] == [0, 1, 2]


@pytest.mark.parametrize(
    "rows, guess",
    [
        (
            "1,0,0,0,0.0035\n2,0.01,0,0,0.0035\n3,0,0.01,0.005,0.0035\n4,0.01,0.01,0,0.0035\n",
            "metres; multiply .* by 1000",
        ),
        ("1,0,0,0,\n2,0.05,0,0,\n3,0,0.05,0.02,\n4,0.05,0.05,0,\n", "metres; multiply .* by 1000"),  # by extent
        ("1,0,0,0,0.138\n2,0.354,0,0,0.138\n3,0,0.354,1.5,0.138\n4,3.9,3.9,3.9,0.138\n", "inches; multiply .* 25.4"),
        ("1,0,0,0,0.0035\n2,10,0,0,0.0035\n3,0,10,5,0.0035\n4,10,10,0,0.0035\n", "metres"),  # diameters in metres
    ],
)
def test_phantom_not_in_mm_is_refused_with_the_guess(tmp_path, rows, guess):
    cfg = make_project(tmp_path)
    (tmp_path / "phantom.csv").write_text("id,x,y,z,diameter\n" + rows)
    with pytest.raises(ConfigError, match=rf"\[phantom\] key 'file': .*phantom.csv: .*looks like {guess}"):
        load_config(cfg)


def test_phantom_in_mm_is_accepted(tmp_path):
    path = tmp_path / "p.csv"
    path.write_text("id,x,y,z,diameter\n1,0,0,0,3.5\n2,9,0,0,3.5\n3,0,9,4.5,3.5\n4,9,9,0,3.5\n")
    assert read_phantom(path).n_beads == 4


def test_a_bead_phantom_of_fewer_than_four_beads_is_refused_naming_the_file(tmp_path, capsys):
    cfg = make_project(tmp_path)
    (tmp_path / "phantom.csv").write_text("id,x,y,z\n1,0,0,0\n2,10,0,0\n3,0,10,0\n")
    rc, err = _cli(["run", cfg], capsys)
    assert rc == 2 and "phantom.csv: a bead phantom needs at least 4 beads; got 3" in err
    assert not (tmp_path / "out").exists() and not (tmp_path / ".fluorocal").exists()


def test_phantom_beads_at_one_point_are_refused(tmp_path):
    path = tmp_path / "p.csv"
    path.write_text("id,x,y,z\n1,0,0,0\n2,10,0,0\n3,10,0,0\n4,0,10,0\n")
    with pytest.raises(InputError, match="lines 3 and 4 place two beads at the same point"):
        read_phantom(path)


# --- config: numbers, names, encodings --------------------------------------------------------


@pytest.mark.parametrize(
    "old, new, match",
    [
        ("pixel_pitch = 0.25", "pixel_pitch = nan", r"'pixel_pitch': expected a positive number \(mm\) in 0.01..5 mm"),
        ("pixel_pitch = 0.25", "pixel_pitch = 250", r"'pixel_pitch': .* in 0.01..5 mm; got 250"),
        (
            "source_image_distance = 1100",
            "source_image_distance = inf",
            r"'source_image_distance': .* in 100..5000 mm; got inf",
        ),
        ("source_image_distance = 1100", "source_image_distance = 1.1", r"in 100..5000 mm; got 1.1"),
        ('name = "A"', 'name = ""', r"key 'name': expected a non-empty name"),
        ('file = "phantom.csv"', 'lattice = "hex"\npitch = nan', r"\[phantom\] key 'pitch': expected a positive"),
        ('file = "phantom.csv"', 'lattice = "hex"\npitch = 0.005', r"'pitch': 0.005 mm looks like metres"),
        ("[phantom]", "calibration = 3\n[phantom]", r"key 'calibration': expected a table \[calibration\]"),
    ],
)
def test_config_numbers_and_names_are_checked_at_load(tmp_path, old, new, match):
    cfg = make_project(tmp_path)
    cfg.write_text(cfg.read_text().replace(old, new, 1))
    with pytest.raises(ConfigError, match=match) as info:
        load_config(cfg)
    assert str(info.value).startswith("project.toml") and "\n" not in str(info.value)


@pytest.mark.parametrize("section", ["output", "cache"])
def test_nul_in_a_folder_name_is_refused_at_load(tmp_path, capsys, section):
    # the attack battery's output_dir_nul and cache_dir_nul: a ValueError traceback from os.stat before
    cfg = make_project(tmp_path, extra_toml=f'\n[{section}]\ndir = "out\\u0000x"\n')
    rc, err = _cli(["run", cfg], capsys)
    assert rc == 2 and f"[{section}] key 'dir'" in err and "NUL character" in err


def test_config_nested_too_deeply_is_one_line(tmp_path, capsys):
    # the attack battery's config_deep_nesting: tomllib's RecursionError was a traceback
    cfg = make_project(tmp_path, extra_toml="x = " + "[" * 5000 + "]" * 5000 + "\n")
    rc, err = _cli(["run", cfg], capsys)
    assert rc == 2 and "project.toml: not a project file (arrays or tables nested too deeply)" in err


def test_non_utf8_config_is_one_line(tmp_path, capsys):
    cfg = make_project(tmp_path)
    cfg.write_bytes(cfg.read_bytes().replace(b'name = "A"', b'name = "\xe9"'))
    rc, err = _cli(["run", cfg], capsys)
    assert rc == 2 and "project.toml: not UTF-8 text (byte 0xe9" in err and "save it as UTF-8" in err


def test_config_with_byte_order_mark_loads(tmp_path):
    cfg = make_project(tmp_path)
    cfg.write_bytes(b"\xef\xbb\xbf" + cfg.read_bytes())
    assert load_config(cfg).systems[0].name == "A"


def test_non_utf8_phantom_is_one_line(tmp_path, capsys):
    cfg = make_project(tmp_path)
    (tmp_path / "phantom.csv").write_bytes(b"id,x,y,z,role\n1,0,0,0,r\xf4le\n2,10,0,0,\n")
    rc, err = _cli(["run", cfg], capsys)
    assert rc == 2 and "phantom.csv: not UTF-8 text" in err


def test_phantom_with_byte_order_mark_reads(tmp_path):
    path = tmp_path / "p.csv"
    path.write_text("\ufeffid,x,y,z\n1,0,0,0\n2,10,0,0\n3,0,10,0\n4,0,0,10\n", encoding="utf-8")
    assert list(read_phantom(path).ids) == [1, 2, 3, 4]


@pytest.mark.parametrize("cell", ["nan", "inf", "-inf"])
def test_non_finite_phantom_coordinate_names_the_line(tmp_path, cell):
    path = tmp_path / "p.csv"
    path.write_text(f"id,x,y,z\n1,0,0,0\n2,{cell},0,0\n3,0,10,0\n")
    with pytest.raises(InputError, match=rf"p.csv:3: column x must be a finite number; got {cell}"):
        read_phantom(path)


@pytest.mark.parametrize("scale", [1000.0, 1e300])
def test_phantom_larger_than_any_field_is_refused(tmp_path, scale):
    # the attack battery's phantom_x1000 (singular normal equations after 78 s of work), phantom_huge_x (1e300:
    # scipy's k-d tree overflowed with a traceback): a phantom spanning more than 2 m is in a smaller unit
    path = tmp_path / "p.csv"
    path.write_text(f"id,x,y,z\n1,0,0,0\n2,{10 * scale:g},0,0\n3,0,{10 * scale:g},{5 * scale:g}\n")
    with pytest.raises(InputError, match=r"p.csv: the phantom spans .* mm, more than any fluoroscope images"):
        read_phantom(path)


def test_non_positive_bead_diameter_is_refused(tmp_path):
    path = tmp_path / "p.csv"
    path.write_text("id,x,y,z,diameter\n1,0,0,0,3\n2,10,0,0,-3\n")
    with pytest.raises(InputError, match=r"p.csv:3: diameter must be a positive number of mm"):
        read_phantom(path)


def test_huge_phantom_is_refused_without_reading_it_all(tmp_path, monkeypatch):
    monkeypatch.setattr(tables, "MAX_PHANTOM_BEADS", 1000)  # the real bound (100 000) reads the same way
    path = tmp_path / "p.csv"
    path.write_text("id,x,y,z\n" + "".join(f"{i},{i % 97},{i // 97},0\n" for i in range(5000)))
    with pytest.raises(InputError, match="more than 1000 phantom rows"):
        read_phantom(path)
    assert tables.read_table(path, tables.PHANTOM)["id"].size == 5000  # no bound for the other readers


def test_phantom_bound_is_a_hundred_thousand_beads():
    assert tables.MAX_PHANTOM_BEADS == 100_000


# --- files and folders --------------------------------------------------------------------------


def test_glob_matching_a_folder_is_refused(tmp_path, capsys):
    cfg = make_project(tmp_path)
    (tmp_path / "frames" / "old").mkdir()
    cfg.write_text(cfg.read_text().replace("frames/*.tif", "frames/*"))
    rc, err = _cli(["run", cfg], capsys)
    assert rc == 2 and "'frames/*' matches the folder" in err and "frames/old" in err


@pytest.mark.parametrize("listed", [False, True])
def test_frame_that_is_a_device_is_refused_at_load(tmp_path, listed):
    # the attack battery's frame_symlink_devzero: a frame linked to /dev/zero was hashed for ever
    cfg = make_project(tmp_path)
    (tmp_path / "frames" / "f1.tif").unlink()
    (tmp_path / "frames" / "f1.tif").symlink_to("/dev/zero")
    if listed:
        cfg.write_text(cfg.read_text().replace('"frames/*.tif"', '["frames/f0.tif", "frames/f1.tif"]'))
    with pytest.raises(ConfigError, match=r"frames/f1.tif is not a regular file"):
        load_config(cfg)


def test_frame_list_naming_a_folder_is_refused(tmp_path):
    cfg = make_project(tmp_path)
    cfg.write_text(cfg.read_text().replace('"frames/*.tif"', '["frames/f0.tif", "frames"]'))
    with pytest.raises(ConfigError, match="frames is a folder; list frame files"):
        load_config(cfg)


@pytest.mark.parametrize("section", ["output", "cache"])
def test_output_or_cache_path_that_is_a_file_is_refused_at_load(tmp_path, capsys, section):
    cfg = make_project(tmp_path, extra_toml=f'\n[{section}]\ndir = "taken/sub"\n')
    (tmp_path / "taken").write_text("a file")
    rc, err = _cli(["run", cfg], capsys)
    assert rc == 2 and f"[{section}] key 'dir'" in err and "taken is a file, not a folder" in err
    assert not (tmp_path / "out").exists() and not (tmp_path / ".fluorocal").exists()


@pytest.mark.parametrize("section, folder", [("output", "out"), ("cache", ".fluorocal")])
def test_read_only_output_or_cache_is_refused_at_load(tmp_path, monkeypatch, section, folder):
    cfg = make_project(tmp_path)
    (tmp_path / folder).mkdir()
    real_access = os.access
    # root may write anywhere, so a read-only folder is simulated
    monkeypatch.setattr(os, "access", lambda p, mode: Path(p).name != folder and real_access(p, mode))
    with pytest.raises(ConfigError, match=rf"\[{section}\] key 'dir': .*{folder} is not writable; fix its permissions"):
        load_config(cfg)


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_project_is_refused_for_real(tmp_path):
    cfg = make_project(tmp_path)
    tmp_path.chmod(0o555)
    try:
        with pytest.raises(ConfigError, match="is not writable"):
            load_config(cfg)
    finally:
        tmp_path.chmod(0o755)


@pytest.mark.parametrize("side", [1, 3])
def test_frames_too_small_for_a_bead_are_refused(tmp_path, side):
    cfg = make_project(tmp_path)
    write_still(tmp_path / "frames" / "f1.tif", np.full((side, side), 100, np.uint16))
    with pytest.raises(InputError, match=rf"f1.tif: frame of {side}x{side} px is too small .*{MIN_FRAME_PX} px"):
        frame_units(load_config(cfg))


def test_frame_sizes_differing_within_a_system_are_refused(tmp_path):
    cfg = make_project(tmp_path)
    write_still(tmp_path / "frames" / "f2.tif", np.full((12, 10), 100, np.uint16))
    with pytest.raises(InputError, match=r"differ in size: .*f0.tif is 10x8 px, .*f2.tif is 10x12 px"):
        frame_units(load_config(cfg))


@pytest.mark.parametrize("content", [b"II*\x00" + bytes(range(200)), b"", b"\x89PNG\r\n\x1a\n truncated"])
def test_corrupt_frame_file_is_named(tmp_path, capsys, content):
    cfg = make_project(tmp_path)
    (tmp_path / "frames" / "f1.tif").write_bytes(content)
    rc, err = _cli(["run", cfg], capsys)
    assert rc == 2 and "f1.tif" in err


# --- the file system at run time -------------------------------------------------------------


def test_full_disk_is_one_line_naming_the_file(tmp_path, capsys, monkeypatch):
    write_still(tmp_path / "f.tif", np.full((32, 32), 1000, np.uint16))

    def full_disk(fh):  # the CSV writer of the detections table finds the disk full
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(tables, "csv", SimpleNamespace(writer=full_disk))
    rc, err = _cli(["detect", tmp_path / "f.tif", "--out", tmp_path], capsys)
    assert rc == 2
    assert err.startswith(f"fluorocal: error: no space left on device writing {tmp_path / 'detections.csv'}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.tif"]  # nothing half-written


def test_atomic_write_names_the_target_not_the_temporary(tmp_path):
    def fail(tmp):
        raise OSError(errno.ENOSPC, "No space left on device", tmp)

    with pytest.raises(OSError, match="No space left") as info:
        atomic.atomic_write(tmp_path / "a.csv", fail)
    assert info.value.filename == str(tmp_path / "a.csv") and info.value.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "exc, expected",
    [
        (PermissionError(errno.EACCES, "Permission denied", "/p/out"), "permission denied: /p/out; fix its"),
        (IsADirectoryError(errno.EISDIR, "Is a directory", "/p/out.json"), "is a directory: /p/out.json"),
        (OSError(errno.ENOSPC, "No space left on device"), "no space left on device writing a file"),
    ],
)
def test_any_os_error_is_one_line_exit_2_and_raised_with_debug(tmp_path, capsys, monkeypatch, exc, expected):
    import fluorocal.cli as cli

    def boom(args):
        raise exc

    cfg = make_project(tmp_path)
    monkeypatch.setattr(cli, "cmd_run", boom)
    rc, err = _cli(["run", cfg], capsys)
    assert rc == 2 and err.startswith(f"fluorocal: error: {expected}")
    with pytest.raises(type(exc)):
        main(["--debug", "run", str(cfg)])


def test_integer_too_large_for_64_bits_names_the_line(tmp_path):
    path = tmp_path / "p.csv"
    path.write_text(f"id,x,y,z\n1,0,0,0\n{2**63},10,0,0\n")
    with pytest.raises(InputError, match=r"p.csv:3: not an integer in column id"):
        read_phantom(path)


@pytest.mark.check  # every frame's labelling search fails in full: 6-25 min of CPU on this machine
def test_a_system_with_no_frame_labelled_is_one_line(tmp_path, capsys):
    """4 frames of 256 px: no frame can be labelled, and the run ends in one line (found in review).

    The sequence labelling had no frame to start from and raised an IndexError.
    """
    from fluorocal.cmd_simulate import write_dataset
    from fluorocal.stages.simulate import SimulateParams, simulate

    write_dataset(simulate(SimulateParams(n_frames=4, n_systems=2, image_size_px=256, seed=0)), tmp_path / "p")
    rc, err = _cli(["--quiet", "run", tmp_path / "p" / "fluorocal.toml", "--jobs", "1"], capsys)
    assert rc == 2 and "could be labelled" in err


@pytest.mark.parametrize("size", [10_000_000, 15])
def test_simulate_refuses_an_image_size_beyond_memory(tmp_path, capsys, size):
    # the attack battery's simulate_image_size_huge: --image-size 10000000 died allocating 728 TiB (traceback)
    rc, err = _cli(["simulate", tmp_path / "sim", "--image-size", size, size], capsys)
    assert rc == 2 and "--image-size: image_size_px must lie in 16..16384" in err
    assert not (tmp_path / "sim").exists() or not any((tmp_path / "sim").iterdir())
