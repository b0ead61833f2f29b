"""Config validation: every error names the file and the key, and says what was expected."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
from fluorocal.config import ConfigError, load_config, params_from_dict

from tests.pipeline.toy import make_project


@dataclass(frozen=True)
class DetectLike:
    min_diameter_px: float = 6.0
    polarity: str = "auto"


def test_valid_config_resolves_paths_relative_to_file(tmp_path):
    cfg = load_config(make_project(tmp_path))
    assert [f.name for f in cfg.systems[0].frames] == ["f0.tif", "f1.tif", "f2.tif"]
    assert cfg.phantom.file == tmp_path / "phantom.csv"
    assert cfg.cache_dir == tmp_path / ".fluorocal" and cfg.output_dir == tmp_path / "out"
    assert cfg.systems[0].pixel_pitch_mm == 0.25 and cfg.scheme == "knn+iop+smooth"


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda t: t + "\nbogus = 1\n", r"key 'bogus': unknown key"),
        (
            lambda t: t.replace("pixel_pitch = 0.25", 'pixel_pitch = "0.25mm"'),
            r"\[\[systems\]\] #1 key 'pixel_pitch': expected a positive number \(mm\)",
        ),
        (
            lambda t: t.replace("pixel_pitch = 0.25", "pixel_pitch = -1"),
            r"key 'pixel_pitch': expected a positive number",
        ),
        (lambda t: t.replace("frames/*.tif", "nothing/*.tif"), r"key 'frames': no file matches 'nothing/\*.tif'"),
        (lambda t: t.replace('"phantom.csv"', '"missing.csv"'), r"\[phantom\] key 'file': phantom file not found"),
        (
            lambda t: t + '\n[calibration]\nscheme = "magic"\n',
            r"\[calibration\] key 'scheme': expected one of none, knn",
        ),
        (
            lambda t: t + "\n[detect]\nmin_diameter = 3\n",
            r"\[detect\] key 'min_diameter': unknown; allowed keys are min_diameter_px, polarity",
        ),
        (lambda t: t + '\n[detect]\nmin_diameter_px = "big"\n', r"\[detect\] key 'min_diameter_px': expected float"),
        (lambda t: t.replace('name = "A"', 'name = "A"\ncolour = "red"'), r"#1 key 'colour': unknown key"),
        (lambda t: t.replace('name = "A"', 'name = "A"\nseeds = "seeds.csv"'), r"#1 key 'seeds': seeds file not found"),
        (lambda t: t + "\n[[systems", r"not valid TOML"),
    ],
)
def test_errors_name_the_key(tmp_path, edit, match):
    path = make_project(tmp_path)
    path.write_text(edit(path.read_text()))
    with pytest.raises(ConfigError, match=match) as info:
        load_config(path, stage_params_allowed={"detect": DetectLike})
    assert "\n" not in str(info.value)
    assert str(info.value).startswith("project.toml")


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "nope.toml")


def test_grid_phantom_needs_lattice_and_pitch(tmp_path):
    path = make_project(tmp_path)
    path.write_text(path.read_text().replace('file = "phantom.csv"', 'lattice = "hex"'))
    with pytest.raises(ConfigError, match=r"\[phantom\] key 'pitch'"):
        load_config(path)
    path.write_text(path.read_text().replace('lattice = "hex"', 'lattice = "hex"\npitch = 5.0'))
    assert load_config(path).phantom.pitch_mm == 5.0


def test_params_from_dict_coerces_ints_to_floats_and_keeps_defaults():
    p = params_from_dict(DetectLike, {"min_diameter_px": 8})
    assert p == DetectLike(min_diameter_px=8.0) and isinstance(p.min_diameter_px, float)


@pytest.mark.parametrize("scheme", ["polynomial", "knn", "knn+smooth"])
def test_a_grid_plate_refuses_a_scheme_it_would_not_use(tmp_path, scheme):
    """A plate is calibrated by its own solve; another scheme was silently replaced by it."""
    path = make_project(tmp_path)
    text = path.read_text().replace('file = "phantom.csv"', 'lattice = "hex"\npitch = 5.0')
    path.write_text(text + f'\n[calibration]\nscheme = "{scheme}"\n')
    with pytest.raises(ConfigError, match=r"\[calibration\] key 'scheme': a grid plate is calibrated by"):
        load_config(path)
    path.write_text(text + '\n[calibration]\nscheme = "none"\n')
    assert load_config(path).scheme == "none"


def test_polynomial_scheme_is_accepted(tmp_path):
    path = make_project(tmp_path)
    path.write_text(path.read_text() + '\n[calibration]\nscheme = "polynomial"\n')
    assert load_config(path).scheme == "polynomial"


@pytest.mark.parametrize(
    "section, key, value, owner",
    [
        ("adjust", "estimate_iop", "false", r"\[calibration\] scheme"),
        ("learn", "smooth", "false", r"\[calibration\] scheme"),
        ("label", "source_image_distance_mm", "1000.0", r"\[\[systems\]\] source_image_distance"),
        ("label", "pixel_pitch_mm", "0.3", r"\[\[systems\]\] pixel_pitch"),
    ],
)
def test_a_key_another_setting_owns_is_refused_naming_both(tmp_path, section, key, value, owner):
    """Such keys used to be accepted, hashed and then silently overridden."""
    from fluorocal.graph import stage_params_classes

    path = make_project(tmp_path)
    path.write_text(path.read_text() + f"\n[{section}]\n{key} = {value}\n")
    with pytest.raises(ConfigError, match=rf"\[{section}\] key '{key}': set by {owner}") as info:
        load_config(path, stage_params_allowed=stage_params_classes())
    assert "\n" not in str(info.value)


def test_the_config_schema_and_cli_take_exactly_the_kinds_spellings(tmp_path):
    """``[phantom] lattice``, its config reference line and ``label --lattice``: each a kind's spelling, all of them.

    The spellings' one home is the kinds' table; the truth is the grid plate's two lattices (hex, square).
    """
    import re

    from fluorocal.cli import build_parser
    from fluorocal.config_schema import SCHEMA
    from fluorocal.stages.kinds import KINDS, phantom_kind

    spellings = sorted(s for s in KINDS if s)  # "": a phantom file, spelled by no lattice
    assert spellings == ["hex", "square"]
    for spelling in spellings:
        path = make_project(tmp_path / spelling)
        path.write_text(path.read_text().replace('file = "phantom.csv"', f'lattice = "{spelling}"\npitch = 5.0'))
        assert load_config(path).phantom.kind is phantom_kind(spelling)
    path.write_text(path.read_text().replace('lattice = "square"', 'lattice = "triangle"'))
    with pytest.raises(ConfigError, match=r"key 'lattice': expected \"hex\" or \"square\"; got 'triangle'"):
        load_config(path)
    (doc,) = [k.help for k in SCHEMA if (k.section, k.name) == ("phantom", "lattice")]
    assert sorted(re.findall(r'`"(\w+)"`', doc)) == spellings
    label = build_parser()._subparsers._group_actions[0].choices["label"]
    (lattice,) = [a for a in label._actions if "--lattice" in a.option_strings]
    assert sorted(lattice.choices) == spellings
    args = build_parser().parse_args(["label", "d.csv", "--lattice", "hex", "--pitch", "5", "--out", "o"])
    assert args.lattice == "hex"
