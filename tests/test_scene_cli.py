import re
import textwrap

import numpy as np
import pytest

from warpcloth.cli import main
from warpcloth.mesh_io import grid_mesh
from warpcloth.scene import DEFAULT_SCENE, SCENE_NAMES, load_scene, scene_from_toml
from warpcloth.solver.rollout import rollout
from warpcloth.usd import read_usd_points

MINIMAL = """\
name = "test"
[sim]
dt = 0.01
steps = 2
[cloth]
grid = { res = [4, 3], size = [1.0, 0.5] }
material = "gray-interlock"
"""


def _scene(extra: str = "", base: str = MINIMAL, **kwargs):
    return scene_from_toml(base + textwrap.dedent(extra), source="t.toml", **kwargs)


def test_embedded_scene_names():
    assert DEFAULT_SCENE in SCENE_NAMES
    assert {"hanging-wind", "free-fall", "pinned-corners", "flag", "damped-hanging"} <= set(SCENE_NAMES)


@pytest.mark.parametrize("name", SCENE_NAMES)
def test_every_embedded_scene_loads(name):
    scene = load_scene(name)
    assert scene.name == name and scene.description
    assert scene.dt > 0 and scene.steps >= 1
    model = scene.model_builder.finalize(device="cpu")
    assert model.particle_count > 0


def test_hanging_wind_matches_the_seed_setup():
    scene = load_scene("hanging-wind")
    assert (scene.dt, scene.steps, scene.grid_res) == (0.02, 50, (16, 16))
    model = scene.model_builder.finalize(device="cpu")
    assert model.particle_count == 289 and model.handle_count == 2 and model.pin_count == 0
    x = model.particle_x0.numpy()
    top = x[model.handle_particle.numpy()]
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))  # the sheet is turned 30 degrees out of the wind
    np.testing.assert_allclose(top, [[-0.5 * c, -0.5 * s, 0.5], [0.5 * c, 0.5 * s, 0.5]], atol=1e-6)  # top corners
    assert x[:, 2].min() == pytest.approx(-0.5, abs=1e-6)
    np.testing.assert_allclose(model.gravity.numpy()[0], [0.0, 0.0, -9.8], rtol=1e-6)
    np.testing.assert_allclose(model.wind_velocity.numpy()[0], [5.0, 0.0, 0.0])
    assert model.material_names == ["gray-interlock"]
    assert model.material_thicken.numpy()[0] == 2.0


def test_unknown_embedded_name_lists_names():
    with pytest.raises(ValueError, match="unknown scene 'hanging'") as info:
        load_scene("hanging")
    for name in SCENE_NAMES:
        assert name in str(info.value)


@pytest.mark.parametrize(
    "extra, match",
    [
        ("colour = 'red'\n", r"t.toml: cloth.colour: unknown key; allowed here: grid, mesh"),
        ("[wind]\nvelocity = [1, 0, 0]\nspeed = 3\n", r"wind.speed: unknown key"),
        ("[[handles]]\nparticle = 0\nstifness = 3.0\n", r"handles\[0\].stifness: unknown key"),
        ("[solver]\ncg_tolerance = 1e-3\n", r"solver.cg_tolerance: unknown key"),
    ],
)
def test_unknown_key_names_key_path(extra, match):
    with pytest.raises(ValueError, match=match):
        _scene(extra)


def test_unknown_top_level_key():
    with pytest.raises(ValueError, match=r"t.toml: colour: unknown key; allowed here: name, description"):
        _scene(base="colour = 'red'\n" + MINIMAL)


def test_unknown_nested_key_in_cloth():
    base = MINIMAL.replace('material = "gray-interlock"', 'material = "gray-interlock"\nmaterrial = 3')
    with pytest.raises(ValueError, match=r"cloth.materrial: unknown key"):
        _scene(base=base)


@pytest.mark.parametrize(
    "old, new, match",
    [
        ("steps = 2", 'steps = "two"', r"sim.steps: expected an integer, got string"),
        ("steps = 2", "steps = 2.0", r"sim.steps: expected an integer, got float"),
        ("dt = 0.01", "dt = 0", r"sim.dt: must be > 0"),
        ('material = "gray-interlock"', "material = 3", r"cloth.material: expected a string or a table, got integer"),
        ('material = "gray-interlock"', 'material = "grey"', r"cloth.material: unknown material preset 'grey'"),
        ("res = [4, 3]", "res = [4, 0]", r"cloth.grid.res\[1\]: must be >= 1"),
        ("size = [1.0, 0.5]", "size = [1.0]", r"cloth.grid.size: expected an array of 2 numbers"),
        ('name = "test"', "name = 1", r"name: expected a string"),
        (
            'material = "gray-interlock"',
            "material = { density = 0.2, stretching = [[1,1,1,1]], bending = [[1,1,1,1,1]] }",
            r"cloth.material.stretching: expected 6 rows",
        ),
        (
            'material = "gray-interlock"',
            "material = { density = 0.2, stretch_stiffness = -1.0, shear_stiffness = 1.0, bend_stiffness = 0.0 }",
            r"cloth.material: .*stretch_stiffness",
        ),
        ('material = "gray-interlock"', "material = { colour = 1 }", r"cloth.material: unrecognised material table"),
    ],
)
def test_wrong_type_or_value_names_key_path(old, new, match):
    assert old in MINIMAL
    with pytest.raises(ValueError, match=match):
        _scene(base=MINIMAL.replace(old, new))


def test_missing_and_conflicting_keys():
    with pytest.raises(ValueError, match=r"sim.steps: missing required key"):
        _scene(base=MINIMAL.replace("steps = 2\n", ""))
    with pytest.raises(ValueError, match=r"cloth: give exactly one of 'grid' and 'mesh'"):
        _scene(base=MINIMAL.replace("grid = { res = [4, 3], size = [1.0, 0.5] }\n", ""))
    with pytest.raises(ValueError, match=r"handles\[0\]: give exactly one of"):
        _scene("[[handles]]\nparticle = 0\ngrid_row = 0\n")
    with pytest.raises(ValueError, match=r"pins\[0\].particle: particle 20 out of range"):
        _scene("[[pins]]\nparticle = 20\n")
    with pytest.raises(ValueError, match=r"pins\[0\].grid_vertex\[0\]: index 5 out of range"):
        _scene("[[pins]]\ngrid_vertex = [5, 0]\n")
    with pytest.raises(ValueError, match=r"handles\[0\].motion\[1\]\[0\]: key times must increase"):
        _scene("[[handles]]\nparticle = 0\nmotion = [[0.0, [0, 0, 0]], [0.0, [0, 0, 1]]]\n")
    with pytest.raises(ValueError, match=r"pins\[0\]: particle 1 is also held by handles\[0\]"):
        _scene("[[handles]]\ngrid_column = 1\n[[pins]]\ngrid_row = 0\n")
    with pytest.raises(ValueError, match=r"pins\[1\]: particle 0 is also pinned by pins\[0\]"):
        _scene("[[pins]]\nparticle = 0\n[[pins]]\ngrid_vertex = [0, 0]\n")
    with pytest.raises(ValueError, match=r"invalid TOML"):
        _scene("[sim\n")


def test_selectors_motion_forces_and_solver():
    scene = _scene(
        """
        [[handles]]
        grid_vertex = [-1, -1]
        stiffness = 50.0
        motion = [[0.0, [0, 0, 0]], [1.0, [0, 0, 0.5]]]
        [[handles]]
        grid_column = 2
        [[pins]]
        grid_column = 0
        [[pins]]
        grid_vertex = [4, 0]
        [wind]
        velocity = [0.0, 2.0, 0.0]
        drag = 0.5
        [damping]
        mass = 0.1
        [solver]
        cg_tol = 1e-4
        cg_max_iters = 50
        """,
        base='gravity = [0.0, 0.0, -1.0]\n' + MINIMAL,
    )
    assert scene.solver_options.cg_tol == 1e-4 and scene.solver_options.cg_max_iters == 50
    model = scene.model_builder.finalize(device="cpu")
    # Grid 4 x 3 cells: 5 x 4 vertices, vertex (i, j) = 5 j + i.
    np.testing.assert_array_equal(model.handle_particle.numpy(), [19, 2, 7, 12, 17])
    np.testing.assert_allclose(model.handle_stiffness.numpy(), [50.0, 1e3, 1e3, 1e3, 1e3])
    assert model.handle_motion[0].at(1.0)[2] == pytest.approx(0.5) and model.handle_motion[1] is None
    np.testing.assert_array_equal(np.sort(model.pin_particle.numpy()), [0, 4, 5, 10, 15])
    np.testing.assert_allclose(model.gravity.numpy()[0], [0, 0, -1])
    np.testing.assert_allclose(model.wind_drag.numpy(), [0.5])
    assert model.damping_mass.numpy()[0] == pytest.approx(0.1)


def test_material_table_forms(tmp_path):
    iso = "material = { density = 0.2, stretch_stiffness = 100.0, shear_stiffness = 10.0, bend_stiffness = 1e-5 }"
    scene = _scene(base=MINIMAL.replace('material = "gray-interlock"', iso + "\nthicken = 2"))
    model = scene.model_builder.finalize(device="cpu")
    np.testing.assert_allclose(model.material_stretching.numpy()[0, 0], [50.0, 0.0, 50.0, 5.0])
    assert model.material_thicken.numpy()[0] == 2.0

    mean = 'material = { mean = ["gray-interlock", "11oz-black-denim"] }'
    model = _scene(base=MINIMAL.replace('material = "gray-interlock"', mean)).model_builder.finalize(device="cpu")
    assert model.material_density.numpy()[0] == pytest.approx((0.187 + 0.324) / 2)

    (tmp_path / "mat.json").write_text(
        '{"density": 0.3, "stretching": [[1, 0, 1, 1], [1, 0, 1, 1], [1, 0, 1, 1], [1, 0, 1, 1], [1, 0, 1, 1], '
        '[1, 0, 1, 1]], "bending": [[1, 1, 1, 1, 1], [1, 1, 1, 1, 1], [1, 1, 1, 1, 1]]}'
    )
    file_form = 'material = { file = "mat.json", stretching_mult = 2.0 }'
    scene = _scene(base=MINIMAL.replace('material = "gray-interlock"', file_form), base_dir=tmp_path)
    model = scene.model_builder.finalize(device="cpu")
    assert model.material_stretching.numpy()[0, 0, 0] == 2.0 and model.material_density.numpy()[0] == pytest.approx(0.3)
    with pytest.raises(ValueError, match=r"cloth.material: file not found"):
        missing = MINIMAL.replace('material = "gray-interlock"', 'material = { file = "nope.json" }')
        _scene(base=missing, base_dir=tmp_path)


def test_mesh_cloth_relative_to_scene_file(tmp_path):
    g = grid_mesh(2, 2, 1.0, 1.0)
    lines = [f"v {x} {y} {z}" for x, y, z in g.positions.tolist()]
    lines += [f"vt {x} {y}" for x, y, _ in g.positions.tolist()]
    lines += ["f " + " ".join(f"{i + 1}/{i + 1}" for i in t) for t in g.triangles.tolist()]
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "square.obj").write_text("\n".join(lines) + "\n")
    scene_path = tmp_path / "scene.toml"
    scene_path.write_text(
        MINIMAL.replace(
            "grid = { res = [4, 3], size = [1.0, 0.5] }",
            'mesh = { path = "meshes/square.obj", scale = 2.0 }\nrot_deg = [90.0, 0.0, 0.0]\npos = [0.0, 0.0, 1.0]',
        )
        + "[[pins]]\nparticle = 8\n"
    )
    scene = load_scene(scene_path)
    assert scene.grid_res is None
    model = scene.model_builder.finalize(device="cpu")
    np.testing.assert_allclose(model.particle_x0.numpy()[8], [2.0, 0.0, 3.0], atol=1e-6)  # (2, 2, 0) -> (2, 0, 2) + z 1
    assert model.tri_area.numpy().sum() == pytest.approx(4.0)  # scale applies to material coordinates too
    bad = tmp_path / "bad.toml"
    bad.write_text(MINIMAL + "[[pins]]\ngrid_row = 0\n")
    bad.write_text(bad.read_text().replace("grid = { res = [4, 3], size = [1.0, 0.5] }", 'mesh = "meshes/square.obj"'))
    with pytest.raises(ValueError, match=r"bad.toml: pins\[0\].grid_row: needs a grid cloth"):
        load_scene(bad)
    bad.write_text(scene_path.read_text().replace("meshes/square.obj", "meshes/missing.obj"))
    with pytest.raises(ValueError, match=r"bad.toml: cloth.mesh: file not found: .*missing.obj"):
        load_scene(bad)


def test_cli_simulate_writes_simulated_points(tmp_path):
    out = tmp_path / "out.usda"
    assert main(["simulate", "--steps", "3", "--usd", str(out), "--device", "cpu"]) == 0
    frames = read_usd_points(out)
    assert frames.shape == (4, 289, 3)

    scene = load_scene(DEFAULT_SCENE)
    model, sim = scene.build(device="cpu")
    traj = rollout(sim, model.state(), model.control(), steps=3)
    expected = np.stack([s.particle_x.numpy() for s in traj]).astype(np.float32)
    np.testing.assert_array_equal(frames, expected.astype(np.float64))
    assert not np.allclose(frames[3], frames[0])  # it moved


def test_cli_dt_override_and_default_path(tmp_path, monkeypatch, capsys):
    from pxr import Usd

    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "free-fall", "--steps", "2", "--dt", "0.01", "--device", "cpu"]) == 0
    out = tmp_path / "free-fall.usda"
    assert out.is_file()
    stage = Usd.Stage.Open(str(out))
    assert stage.GetTimeCodesPerSecond() == pytest.approx(100.0) and stage.GetEndTimeCode() == 2
    summary = capsys.readouterr().out
    assert "2 steps" in summary and "CG iterations" in summary and str(out) in summary


def test_cli_scenes_lists_descriptions(capsys):
    assert main(["scenes"]) == 0
    text = capsys.readouterr().out
    for name in SCENE_NAMES:
        assert name in text
    assert load_scene("flag").description in text


@pytest.mark.parametrize(
    "argv, match",
    [
        (["simulate", "no-such-scene"], "unknown scene 'no-such-scene'"),
        (["simulate", "--steps", "0"], "--steps must be >= 1"),
        (["simulate", "--dt", "-1"], "--dt must be"),
    ],
)
def test_cli_errors_are_one_line_exit_2(argv, match, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert match in err and err.count("\n") == 1 and "Traceback" not in err


def test_cli_bad_scene_file(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text(MINIMAL + "[wind]\nvelocity = [1, 0]\n")
    assert main(["simulate", str(path), "--usd", str(tmp_path / "x.usda")]) == 2
    err = capsys.readouterr().err
    assert "wind.velocity: expected an array of 3 numbers" in err and err.count("\n") == 1
    assert not (tmp_path / "x.usda").exists()


# -- estimate and control: pointers, the seed's column, progress over jobs ---------------------------------------------

SMALL_TASKS = MINIMAL.replace('name = "test"', 'name = "my-cloth"') + """\
[[pins]]
grid_row = -1
[control]
grid_vertices = [[0, 0]]
interval = 0.01
intervals = 2
loss = { com = [0.0, 0.0, -0.1] }
iters = 3
[estimate]
iters = 1
"""


def test_estimate_points_at_a_page_and_shows_the_seed_only_for_its_task(tmp_path, capsys):
    from pathlib import Path

    from warpcloth.tasks.jobs import ControlJob, EstimateJob

    own = tmp_path / "my-cloth.toml"
    own.write_text(SMALL_TASKS)
    assert main(["estimate", str(own), "--device", "cpu"]) == 0
    out = capsys.readouterr().out
    assert "seed (published" not in out
    page = re.search(r"see (docs/\S+\.md), '([^']+)'", out)
    assert page, out
    text = (Path(__file__).resolve().parents[1] / page[1]).read_text(encoding="utf-8")
    assert f"## {page[2]}\n" in text  # the section the pointer names is on the page
    assert main(["estimate", "--steps", "2", "--iters", "1", "--device", "cpu"]) == 0  # the seed's hanging cloth
    assert "seed (published" in capsys.readouterr().out
    assert EstimateJob().seed_published() is not None and EstimateJob(scene="material-estimation").seed_published()
    assert EstimateJob(scene=str(own)).seed_published() is None and EstimateJob(target="x").seed_published() is None
    assert ControlJob().seed_published("mlp") is not None and ControlJob(scene="basket-throw").seed_published("mlp")
    assert ControlJob(scene=str(own)).seed_published("open-loop") is None
    assert ControlJob(scene="tall-wall-throw").seed_published("open-loop") is None


def test_control_starts_show_progress_by_simulations(tmp_path, capsys):
    own = tmp_path / "my-cloth.toml"
    own.write_text(SMALL_TASKS)
    assert main(["control", str(own), "--starts", "2", "--device", "cpu"]) == 0
    err = capsys.readouterr().err
    assert "6/6 [" in err and "jobs=2/2" in err  # 2 jobs of 3 simulations each


class _CountingJob:
    """A job of ``n`` simulations that records, after each, where the bar over all jobs stands."""

    def __init__(self, n, seen):
        self.n, self.seen = n, seen

    def simulations(self):
        return self.n

    def run(self, progress=False):
        from tqdm import tqdm

        from warpcloth.progress import progress_bar

        with progress_bar(self.n, "inner", "sim") as bar:
            for _ in range(self.n):
                bar.update()
                self.seen.append([b.n for b in tqdm._instances if not b.disable])
        return {}

    def label(self):
        return "counting"


class _SilentJob:
    def run(self):
        return {}

    def label(self):
        return "silent"


def test_jobs_bar_advances_with_each_simulation():
    from warpcloth.tasks.jobs import run_jobs

    seen = []
    results = run_jobs([_CountingJob(3, seen), _SilentJob(), _CountingJob(2, seen)], progress=True)
    assert all(r.ok for r in results)
    # one bar (total 3 + 1 + 2), advanced as each simulation ran; the job that cannot count, by one at its end
    assert seen == [[1], [2], [3], [5], [6]]
