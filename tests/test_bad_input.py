"""Issue 15: bad input tried as a new user would. Each case gets a clear error before any work, and output goes
only where it was asked to (warpcloth/outputs.py). Each test failed before its fix."""

import numpy as np
import pytest
import warp as wp

import warpcloth as wc
from warpcloth.cli import main
from warpcloth.mesh_io import TriangleMesh, load_obj_sequence, obj_sequence_files
from warpcloth.scene import scene_from_toml
from warpcloth.usd import read_usd_points, write_usd

MAT = wc.preset("gray-interlock")
SCENE = """\
name = {name}
[sim]
dt = 0.01
steps = 2
[cloth]
grid = {{ res = [2, 2], size = [1.0, 1.0] }}
material = "gray-interlock"
"""


def grid_builder(res=(2, 2)):
    b = wc.ModelBuilder()
    b.add_cloth_grid(res, (1.0, 1.0), material=MAT)
    return b


def one_line_error(capsys, argv, match):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert match in err and err.count("\n") == 1 and "Traceback" not in err, err


# -- where output goes -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["../escaped", "/tmp/abs", "", ".hidden", "a/b"])
def test_scene_name_cannot_choose_where_output_goes(name):
    with pytest.raises(ValueError, match="name: .* must be a plain file name"):
        scene_from_toml(SCENE.format(name=f'"{name}"'))


def test_plain_scene_names_load():
    assert scene_from_toml(SCENE.format(name='"my-scene_2.v1"')).name == "my-scene_2.v1"


def test_simulate_refuses_a_non_usd_path_before_simulating(tmp_path, capsys):
    notes = tmp_path / "notes.txt"
    notes.write_text("keep me")
    one_line_error(capsys, ["simulate", "--steps", "1", "--usd", str(notes)], "expected a file ending in .usd")
    assert notes.read_text() == "keep me"
    one_line_error(capsys, ["simulate", "--steps", "1", "--usd", str(tmp_path)], "is a directory")
    one_line_error(capsys, ["simulate", "--steps", "1", "--usd", str(tmp_path / "x.usdz")], ".usd or .usda")


def test_every_output_flag_creates_missing_directories_up_front(tmp_path, capsys):
    # estimate refuses a bad path before the fit, and creates a missing directory (the rule of simulate --usd)
    one_line_error(capsys, ["estimate", "--iters", "1", "--steps", "2", "--json", str(tmp_path / "r.txt")], ".json")
    one_line_error(capsys, ["estimate", "--iters", "1", "--steps", "2", "--plot", str(tmp_path)], "is a directory")
    blocker = tmp_path / "file"
    blocker.write_text("")
    one_line_error(capsys, ["control", "--iters", "1", "--json", str(blocker / "r.json")], "is a file")
    out = tmp_path / "new" / "dir" / "r.json"
    assert main(["estimate", "--iters", "1", "--steps", "2", "--json", str(out)]) == 0
    assert out.exists()


def test_estimate_refuses_zero_steps(capsys):
    one_line_error(capsys, ["estimate", "--steps", "0"], "--steps must be >= 1")


def test_write_usd_checks_its_path(tmp_path):
    tri, frames = np.array([[0, 1, 2]]), [np.eye(3)]
    for path, match in ((tmp_path / "notes.txt", "expected a file ending in"), (tmp_path / "x.usdz", ".usdc")):
        with pytest.raises(ValueError, match=match):
            write_usd(path, triangles=tri, frames=frames, fps=10.0)


def test_a_run_whose_frames_do_not_fit_is_refused_up_front(capsys, tmp_path):
    one_line_error(capsys, ["simulate", "free-fall", "--steps", "100000000", "--usd", str(tmp_path / "f.usda")],
                   "simulate at most")
    assert not (tmp_path / "f.usda").exists()


def test_a_failing_run_writes_the_frames_before_the_failure(tmp_path, capsys):
    # free fall passes a 0.25 m/s speed limit at step 3: the initial frame and steps 1-2 are kept, and the error
    # says it is the speed limit, not necessarily a divergence
    path = tmp_path / "fall.toml"
    path.write_text(SCENE.format(name='"fall"').replace("steps = 2", "steps = 10") + "[solver]\nmax_speed = 0.25\n")
    usd = tmp_path / "fall.usda"
    assert main(["simulate", str(path), "--usd", str(usd)]) == 1
    err = capsys.readouterr().err
    assert "step 3" in err and "max_speed = 0.25" in err and "wrote the 3 frames before it" in err
    frames = read_usd_points(usd)
    assert len(frames) == 3 and frames[2][:, 2].max() < frames[0][:, 2].max()


def test_dt_override_keeps_the_presets_ceiling(tmp_path, capsys):
    path = tmp_path / "s.toml"
    path.write_text(SCENE.format(name='"s"').replace("dt = 0.01", "dt = 0.002") + '[solver]\npreset = "accurate"\n')
    usd = tmp_path / "s.usda"
    assert main(["simulate", str(path), "--usd", str(usd)]) == 0  # the scene's own dt is within the ceiling
    capsys.readouterr()
    one_line_error(capsys, ["simulate", str(path), "--dt", "0.05", "--usd", str(usd)],
                   "--dt: scene 's' uses a solver preset that steps at most 0.0025 s, got 0.05 s")


# -- the API -------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("particle", [2.5, "3", True])
def test_handle_index_must_be_an_integer(particle):
    with pytest.raises(TypeError, match="particle must be an integer index"):
        grid_builder().add_handle(particle)


def test_a_particle_gets_one_handle():
    b = grid_builder()
    b.add_handle(np.int64(2))
    with pytest.raises(ValueError, match="particle 2 has a handle already"):
        b.add_handle(2)


def test_handles_flag_names_a_vertex_twice(capsys, tmp_path):
    (tmp_path / "0.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "1.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    one_line_error(capsys, ["estimate", "--target", str(tmp_path), "--handles", "2,2"], "names a vertex twice")
    one_line_error(capsys, ["estimate", "--target", str(tmp_path), "--handles", "a"], "vertex indices separated")


def test_material_must_be_a_material():
    with pytest.raises(TypeError, match=r"warpcloth.preset\('gray-interlock'\)"):
        wc.ModelBuilder().add_cloth_grid((2, 2), (1.0, 1.0), material="gray-interlock")


def test_a_model_too_large_is_refused_before_allocating():
    with pytest.raises(ValueError, match=r"10,000,200,001 particles, more than ModelBuilder.max_particles"):
        wc.ModelBuilder().add_cloth_grid((100000, 100000), (1.0, 1.0), material=MAT)
    b = wc.ModelBuilder()
    b.max_particles = 8
    with pytest.raises(ValueError, match="9 particles"):
        b.add_cloth_grid((2, 2), (1.0, 1.0), material=MAT)


def test_unused_vertex_and_repeated_triangle_are_refused():
    positions = np.array([(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (5.0, 5.0, 5.0)])
    with pytest.raises(ValueError, match=r"cloth vertex 3 at \[5.0, 5.0, 5.0\] is in no triangle"):
        wc.ModelBuilder().add_cloth_mesh(TriangleMesh(positions=positions, triangles=np.array([[0, 1, 2]])),
                                         material=MAT)
    with pytest.raises(ValueError, match=r"triangle 1 \[0, 2, 1\] repeats triangle 0 \[0, 1, 2\]"):
        wc.ModelBuilder().add_cloth_mesh(TriangleMesh(positions=positions[:3],
                                                      triangles=np.array([[0, 1, 2], [0, 2, 1]])), material=MAT)


def test_step_refuses_a_state_of_another_model():
    small, large = grid_builder((2, 2)).finalize("cpu"), grid_builder((3, 3)).finalize("cpu")
    sim = wc.Simulator(small, 0.01)
    with pytest.raises(ValueError, match=r"state_in.particle_x holds 16 .* the model has 9 particles"):
        sim.step(large.state(), small.empty_state())
    with pytest.raises(ValueError, match=r"state_out.particle_x holds 9 vec3d"):
        sim.step(small.state(), grid_builder((2, 2)).finalize("cpu", dtype=wp.float64).empty_state())


def test_target_frames_are_read_in_numeric_order(tmp_path):
    for k in (0, 1, 2, 10, 11):
        (tmp_path / f"{k}.obj").write_text(f"v {k} 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    files = obj_sequence_files(tmp_path)
    assert [f.name for f in files] == ["0.obj", "1.obj", "2.obj", "10.obj", "11.obj"]


def test_a_non_finite_target_frame_is_named(tmp_path):
    (tmp_path / "0.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "1.obj").write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="frame 1.obj: vertex 1 has a non-finite position"):
        load_obj_sequence(obj_sequence_files(tmp_path))


def test_progress_bars_silence_warps_module_lines_while_open():
    from warpcloth.progress import progress_bar

    before = wp.config.log_level
    try:
        wp.config.log_level = wp.LOG_INFO  # Warp's default: "Module ... load" lines printed
        with progress_bar(2, "test", "step") as bar:
            assert wp.config.log_level == wp.LOG_WARNING
            bar.update(2)
        assert wp.config.log_level == wp.LOG_INFO
    finally:
        wp.config.log_level = before
