import json
import math

import numpy as np
import pytest
from conftest import seed_data

from warpcloth.materials import (
    DIFFCLOTH_BENDING_SCALE,
    DIFFCLOTH_STRETCHING_SCALE,
    PRESET_NAMES,
    SEED_INITIAL_GUESS_NAMES,
    Material,
    load_material_json,
    mean_material,
    preset,
)


def _valid_tables():
    return dict(density=0.2, stretching=np.full((6, 4), 10.0), bending=np.full((3, 5), 1e-5))


def test_preset_names():
    assert len(PRESET_NAMES) == 10
    assert len(SEED_INITIAL_GUESS_NAMES) == 8
    assert "royal-target" not in SEED_INITIAL_GUESS_NAMES and "white-dots-on-blk" not in SEED_INITIAL_GUESS_NAMES


@pytest.mark.parametrize("name", PRESET_NAMES)
def test_presets_equal_arcsim_files(name):
    data = json.loads((seed_data("materials") / f"{name}.json").read_text())
    m = preset(name)
    assert m.name == name and m.thicken == 1.0
    assert m.density == data["density"]
    np.testing.assert_array_equal(m.stretching, np.array(data["stretching"]))
    np.testing.assert_array_equal(m.bending, np.array(data["bending"]))
    assert m.stretching.dtype == np.float64 and m.bending.dtype == np.float64


def test_load_material_json_matches_preset():
    m = load_material_json(seed_data("materials") / "gray-interlock.json", thicken=2.0)
    p = preset("gray-interlock", thicken=2.0)
    assert m.name == "gray-interlock" and m.thicken == 2.0
    np.testing.assert_array_equal(m.stretching, p.stretching)
    np.testing.assert_array_equal(m.bending, p.bending)


def test_mean_of_eight_is_seed_initial_guess():
    init = load_material_json(
        seed_data("materials") / "init_mat.json",
        stretching_mult=DIFFCLOTH_STRETCHING_SCALE,
        bending_mult=DIFFCLOTH_BENDING_SCALE,
    )
    mean = mean_material(SEED_INITIAL_GUESS_NAMES)
    assert math.isclose(mean.density, init.density, rel_tol=1e-6)
    np.testing.assert_allclose(mean.stretching, init.stretching, rtol=1e-6, atol=0)
    np.testing.assert_allclose(mean.bending, init.bending, rtol=1e-6, atol=0)


def test_spec_example_values():
    # SPEC.md 1.5: gray-interlock raw stretching row 0 and bending row 0.
    m = preset("gray-interlock")
    np.testing.assert_allclose(m.stretching[0], [16.59, -14.70, 34.48, 36.86], atol=5e-3)
    np.testing.assert_allclose(m.bending[0], np.array([23.2, 32.9, 34.4, 39.0, 23.4]) * 1e-6, atol=5e-8)


def test_load_material_json_mults_and_errors(tmp_path):
    path = tmp_path / "m.json"
    tables = _valid_tables()
    path.write_text(json.dumps({k: np.asarray(v).tolist() for k, v in tables.items()}))
    m = load_material_json(path, stretching_mult=2.0, bending_mult=3.0, thicken=2.0)
    np.testing.assert_allclose(m.stretching, 20.0)
    np.testing.assert_allclose(m.bending, 3e-5)
    assert m.density == 0.2 and m.thicken == 2.0

    path.write_text(json.dumps({"density": 0.2, "stretching": tables["stretching"].tolist()}))
    with pytest.raises(ValueError, match="missing key 'bending'"):
        load_material_json(path)
    extra = {k: np.asarray(v).tolist() for k, v in tables.items()} | {"damping": 0.1}
    path.write_text(json.dumps(extra))
    with pytest.raises(ValueError, match="'damping'"):
        load_material_json(path)
    with pytest.raises(ValueError, match="stretching_mult"):
        load_material_json(path, stretching_mult=-1.0)


def test_unknown_preset_lists_names():
    with pytest.raises(ValueError, match="gray-interlock") as info:
        preset("grey-interlock")
    assert "grey-interlock" in str(info.value)
    with pytest.raises(ValueError, match="valid names"):
        mean_material(["gray-interlock", "nope"])
    with pytest.raises(ValueError, match="empty"):
        mean_material([])
    with pytest.raises(ValueError, match="sequence"):
        mean_material("gray-interlock")


@pytest.mark.parametrize(
    "change, match",
    [
        (dict(density=0.0), "density must be > 0"),
        (dict(density=-1.0), "density must be > 0"),
        (dict(density=float("nan")), "density is not finite"),
        (dict(thicken=0.0), "thicken must be > 0"),
        (dict(thicken=float("inf")), "thicken is not finite"),
        (dict(stretching=np.zeros((5, 4))), r"stretching must have shape \(6, 4\)"),
        (dict(bending=np.zeros((3, 4))), r"bending must have shape \(3, 5\)"),
        (dict(stretching=[[1.0, 2.0], [3.0]]), "stretching must be a 6x4 table"),
    ],
)
def test_validation_errors(change, match):
    kwargs = _valid_tables() | change
    with pytest.raises(ValueError, match=match):
        Material(**kwargs)


@pytest.mark.parametrize("row, col", [(0, 0), (3, 2), (5, 0)])
def test_negative_stretch_entry_names_the_entry(row, col):
    tables = _valid_tables()
    tables["stretching"][row, col] = -1.0
    with pytest.raises(ValueError, match=rf"stretching\[{row}, {col}\]"):
        Material(**tables)


@pytest.mark.parametrize("row, col", [(0, 1), (4, 3)])
def test_negative_coupling_and_shear_are_allowed(row, col):
    tables = _valid_tables()
    tables["stretching"][row, col] = -5.0
    Material(**tables).validate()


def test_non_finite_and_negative_bending_name_the_entry():
    tables = _valid_tables()
    tables["stretching"][2, 3] = np.nan
    with pytest.raises(ValueError, match=r"stretching\[2, 3\] is not finite"):
        Material(**tables)
    tables = _valid_tables()
    tables["bending"][1, 4] = np.inf
    with pytest.raises(ValueError, match=r"bending\[1, 4\] is not finite"):
        Material(**tables)
    tables = _valid_tables()
    tables["bending"][2, 0] = -1e-6
    with pytest.raises(ValueError, match=r"bending\[2, 0\] must be >= 0"):
        Material(**tables)


def test_validate_catches_later_mutation():
    m = preset("gray-interlock")
    m.bending[0, 0] = -1.0
    with pytest.raises(ValueError, match=r"bending\[0, 0\]"):
        m.validate()


def test_isotropic_fills_tables():
    m = Material.isotropic(
        density=0.3,
        stretch_stiffness=100.0,
        shear_stiffness=20.0,
        poisson_coupling=10.0,
        bend_stiffness=2e-5,
        thicken=2.0,
    )
    np.testing.assert_array_equal(m.stretching, np.tile([50.0, 5.0, 50.0, 10.0], (6, 1)))
    np.testing.assert_array_equal(m.bending, np.full((3, 5), 2e-5))
    assert m.density == 0.3 and m.thicken == 2.0 and m.name == "isotropic"


@pytest.mark.parametrize("param", ["stretch_stiffness", "shear_stiffness", "poisson_coupling", "bend_stiffness"])
def test_isotropic_negative_stiffness_names_parameter(param):
    kwargs = dict(density=0.3, stretch_stiffness=100.0, shear_stiffness=20.0, bend_stiffness=2e-5)
    kwargs[param] = -1.0
    with pytest.raises(ValueError, match=param):
        Material.isotropic(**kwargs)


def test_copy_and_scaled_are_independent():
    m = preset("11oz-black-denim", thicken=2.0)
    c = m.copy()
    c.stretching[0, 0] = 0.0
    assert m.stretching[0, 0] != 0.0 and c.thicken == 2.0
    s = m.scaled(density=2.0, stretching=0.5, bending=10.0)
    assert s.density == pytest.approx(2 * m.density)
    np.testing.assert_allclose(s.stretching, 0.5 * m.stretching)
    np.testing.assert_allclose(s.bending, 10.0 * m.bending)
    assert s.thicken == m.thicken
    with pytest.raises(ValueError, match="bending"):
        m.scaled(bending=-1.0)
    with pytest.raises(ValueError, match="density"):
        m.scaled(density=0.0)


def test_constructor_copies_input():
    tables = _valid_tables()
    m = Material(**tables)
    tables["stretching"][0, 0] = 99.0
    assert m.stretching[0, 0] == 10.0
