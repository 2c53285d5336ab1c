"""Material fits of what people record: point clouds and markers instead of every vertex, from code (TrajectoryFit)
and from a scene's [estimate] table."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from conftest import SMALL_SCENE

import warpcloth as wc
from warpcloth import recordings
from warpcloth.observations import MarkerFrames, PointCloudFrames, VertexFrames
from warpcloth.tasks import estimation as E

STRIDE = 3


def _truth() -> wc.Material:
    start = E.initial_guess()
    return wc.Material(density=1.5 * start.density, stretching=start.stretching, bending=start.bending, thicken=2)


def _recorded(tmp_path):
    """The small scene's model and its true vertex frames (every STRIDE steps, frame 0 the start)."""
    path = tmp_path / "base.toml"
    path.write_text(SMALL_SCENE.format(extra=""))
    model = wc.load_scene(path).finalize("cpu", requires_grad=True)
    frames = E.TrajectoryFit.simulate_targets(model, _truth(), steps=12, frame_stride=STRIDE, dt=0.02)
    return model, np.stack(frames)


def test_a_vertex_recording_given_as_an_observation_fits_bitwise_as_plain_frames(tmp_path):
    model, frames = _recorded(tmp_path)
    plain = E.TrajectoryFit(model, list(frames), steps=12, frame_stride=STRIDE)
    observed = E.TrajectoryFit(model, VertexFrames(frames), steps=12, frame_stride=STRIDE)
    start = E.initial_guess()
    a, b = plain.loss_and_grad(start), observed.loss_and_grad(start)
    assert a[0] == b[0] and a[1] == b[1] and np.array_equal(a[2], b[2])
    assert plain.simulation_error(start) == observed.simulation_error(start)


@pytest.mark.parametrize("kind", ["points", "markers"])
def test_a_fit_from_point_clouds_or_markers_moves_the_density_towards_the_truth(tmp_path, kind):
    model, frames = _recorded(tmp_path)
    rng = np.random.default_rng(0)
    triangles = model.triangles_np
    if kind == "points":
        clouds = recordings.point_cloud_recording(frames, triangles, points=200, noise=0.0, drop=0.0, rng=rng)
        observation = PointCloudFrames(clouds)
    else:
        markers = recordings.marker_recording(frames, triangles, markers=6, hidden=0.2, rng=rng)
        observation = MarkerFrames(markers.triangles, markers.barycentric, markers.positions)
    fit = E.TrajectoryFit(model, observation, steps=12, frame_stride=STRIDE, reference=list(frames))
    assert fit.has_reference
    start, truth = E.initial_guess(), _truth()
    result = E.estimate_material(fit, initial=start, iters=6, free=["density"])
    before = abs(start.density - truth.density) / truth.density
    after = abs(result.material.density - truth.density) / truth.density
    assert after < 0.5 * before, (before, after)
    assert result.simulation_error_pct < result.initial_simulation_error_pct


def test_a_batch_of_marker_fits_reports_each_worlds_simulation_error_as_its_fit_alone(tmp_path):
    """estimate_materials over two worlds of the small scene from two starts, one marker recording and one world's
    true frames as the reference for both: each world's fitted and initial simulation errors are its fit's alone."""
    model, frames = _recorded(tmp_path)
    markers = recordings.marker_recording(frames, model.triangles_np, markers=6, hidden=0.2,
                                          rng=np.random.default_rng(3))
    observation = MarkerFrames(markers.triangles, markers.barycentric, markers.positions)
    options = wc.SolverOptions(preconditioner="block_ssor", cg_tol=1e-10)  # a world solved alone as in the batch
    batch = wc.ModelBuilder()
    batch.replicate(wc.load_scene(tmp_path / "base.toml").model_builder, 2, own_materials=True)
    batched = E.TrajectoryFit(batch.finalize("cpu", requires_grad=True), observation, steps=12, frame_stride=STRIDE,
                              options=options, reference=list(frames))
    assert len(batched.reference[0]) == 2 * len(frames[0])  # one world's frames serve both
    starts = [E.initial_guess(), dataclasses.replace(E.initial_guess(), density=2.0 * E.initial_guess().density)]
    results = E.estimate_materials(batched, initial=starts, iters=4, free=["density"], scan=None)
    for start, result in zip(starts, results):
        alone = E.TrajectoryFit(model, observation, steps=12, frame_stride=STRIDE, options=options,
                                reference=list(frames))
        expected = E.estimate_material(alone, initial=start, iters=4, free=["density"], scan=None)
        assert result.losses == expected.losses
        assert math.isfinite(result.simulation_error_pct)
        assert result.simulation_error_pct == pytest.approx(expected.simulation_error_pct, rel=1e-12)
        assert result.initial_simulation_error_pct == pytest.approx(expected.initial_simulation_error_pct, rel=1e-12)
    assert results[0].simulation_error_pct != results[1].simulation_error_pct
    with pytest.raises(ValueError, match="1 materials for 2 worlds"):
        batched.simulation_errors([starts[0]])


def test_a_trimmed_fit_of_a_cloud_with_outliers_ends_where_the_clean_clouds_fit_does(tmp_path):
    """A tenth of each frame's points thrown 10 cm off (flying pixels): the squared loss's density fit is ruined (more
    than 5x the clean fit's error) and Huber's too (2x); trimming 15 % of the points ends where the clean recording's
    fit does."""
    model, frames = _recorded(tmp_path)
    clean = recordings.point_cloud_recording(frames, model.triangles_np, points=200, noise=0.001, drop=0.0,
                                             rng=np.random.default_rng(5))
    rng = np.random.default_rng(6)
    noisy = [c.copy() for c in clean]
    for c in noisy[1:]:
        c[: len(c) // 10] += rng.normal(0.0, 0.1, (len(c) // 10, 3))
    truth = _truth()

    def density_error(clouds, robust=None):
        fit = E.TrajectoryFit(model, PointCloudFrames(clouds, robust=robust), steps=12, frame_stride=STRIDE)
        fitted = E.estimate_material(fit, iters=12, free=["density"]).material
        return abs(fitted.density - truth.density) / truth.density

    reference = density_error(clean)
    assert density_error(noisy, ("trimmed", 0.15)) == pytest.approx(reference, rel=0.02)
    assert density_error(noisy) > 5.0 * reference and density_error(noisy, ("huber", 0.005)) > 2.0 * reference


def test_a_point_cloud_fit_without_a_reference_says_it_cannot_measure_the_simulation_error(tmp_path):
    model, frames = _recorded(tmp_path)
    clouds = recordings.point_cloud_recording(frames, model.triangles_np, points=100, noise=0.0, drop=0.0,
                                              rng=np.random.default_rng(1))
    fit = E.TrajectoryFit(model, PointCloudFrames(clouds), steps=12, frame_stride=STRIDE)
    assert not fit.has_reference
    with pytest.raises(ValueError, match="PointCloudFrames recording holds no vertex positions"):
        fit.simulation_error(E.initial_guess())
    result = E.estimate_material(fit, iters=2, free=["density"])
    assert math.isnan(result.simulation_error_pct) and result.evaluations >= 2


def test_a_scene_reads_a_point_cloud_directory_and_a_marker_file(tmp_path):
    model, frames = _recorded(tmp_path)
    rng = np.random.default_rng(2)
    clouds = recordings.point_cloud_recording(frames, model.triangles_np, points=150, noise=0.001, drop=0.0, rng=rng)
    clouds[2] = None  # a dropped frame: no file
    recordings.write_point_clouds(tmp_path / "clouds", clouds, kind=".npy")
    markers = recordings.marker_recording(frames, model.triangles_np, markers=5, hidden=0.2, rng=rng)
    recordings.write_markers(tmp_path / "markers.json", *markers)
    cases = (('targets = "clouds"\nhuber = 0.01', PointCloudFrames), ('targets = "clouds"\ntrimmed = 0.1',
                                                                      PointCloudFrames),
             ('markers = "markers.json"', MarkerFrames))
    for extra, kind in cases:
        path = tmp_path / "fit.toml"
        path.write_text(SMALL_SCENE.format(extra=f'[estimate]\n{extra}\nframe_stride = {STRIDE}\nfree = ["density"]\n'
                                           'iters = 2\n'))
        task = E.EstimationTask.from_scene(path, device="cpu")
        assert isinstance(task.fit.observation, kind) and task.truth is None
        if "trimmed" in extra:
            assert task.fit.observation.robust == ("trimmed", 0.1)
        assert task.fit.observation.frame_count == len(frames)
        assert task.run().evaluations >= 2


def test_estimate_previews_a_point_cloud_fit_with_its_recorded_points(tmp_path, capsys):
    from warpcloth.cli import main

    model, frames = _recorded(tmp_path)
    clouds = recordings.point_cloud_recording(frames, model.triangles_np, points=100, noise=0.001, drop=0.0,
                                              rng=np.random.default_rng(9))
    recordings.write_point_clouds(tmp_path / "clouds", clouds, kind=".npy")
    path = tmp_path / "fit.toml"
    path.write_text(SMALL_SCENE.format(extra=f'[estimate]\ntargets = "clouds"\nframe_stride = {STRIDE}\n'
                                             'free = ["density"]\niters = 1\n'))
    assert main(["estimate", str(path), "--device", "cpu", "--preview", str(tmp_path / "fit.png")]) == 0
    assert "the recorded points as red dots" in capsys.readouterr().out
    assert (tmp_path / "fit.png").stat().st_size > 0


@pytest.mark.parametrize("extra, message", [
    ('targets = "clouds"\nmarkers = "m.json"', "estimate.markers: a scene fits one recording"),
    ('huber = 0.01', "estimate.huber: applies to a point-cloud recording"),
    ('targets = "clouds"\nhuber = -1.0', "estimate.huber"),
    ('targets = "clouds"\nboth_ways = 1', "estimate.both_ways: expected true or false"),
    ('trimmed = 0.1', "estimate.trimmed: applies to a point-cloud recording"),
    ('targets = "clouds"\ntrimmed = 1.0', "estimate.trimmed: the fraction of points left out must be below 1"),
    ('targets = "clouds"\ntrimmed = 0.0', "estimate.trimmed: must be > 0"),
    ('targets = "clouds"\ntrimmed = 0.1\nhuber = 0.01', "estimate.trimmed: give huber or trimmed, not both"),
    ('frame_count = 5', "estimate.frame_count: applies to a point-cloud recording"),
    ('targets = "clouds"\nframe_count = 4', "estimate.frame_count: 4 frames, but .*clouds holds frame 4"),
])
def test_a_scene_refuses_a_recording_it_cannot_use(tmp_path, extra, message):
    model, frames = _recorded(tmp_path)
    recordings.write_point_clouds(tmp_path / "clouds", [f + 0.0 for f in frames], kind=".npy")
    path = tmp_path / "bad.toml"
    path.write_text(SMALL_SCENE.format(extra=f"[estimate]\n{extra}\nframe_stride = {STRIDE}\n"))
    with pytest.raises(ValueError, match=message):
        wc.load_scene(path)


def test_a_recording_short_of_the_compared_frames_is_refused_naming_what_it_holds(tmp_path):
    model, frames = _recorded(tmp_path)
    recordings.write_point_clouds(tmp_path / "clouds", list(frames[:3]), kind=".ply")
    path = tmp_path / "short.toml"
    path.write_text(SMALL_SCENE.format(extra=f'[estimate]\ntargets = "clouds"\nframe_stride = {STRIDE}\n'))
    with pytest.raises(ValueError, match="compare 5 frames .* holds 3"):
        wc.load_scene(path)
    # its last two frames dropped, said by frame_count: they count as dropped, not missing
    path.write_text(SMALL_SCENE.format(extra=f'[estimate]\ntargets = "clouds"\nframe_stride = {STRIDE}\n'
                                             'frame_count = 5\n'))
    points = wc.load_scene(path).estimate.targets.points
    assert len(points) == 5 and points[3] is None and points[4] is None and points[2] is not None


def test_a_scene_registers_its_start_to_the_first_point_cloud(tmp_path):
    """The recording starts with the cloth swung out and moving (the truth launched across its plane, recorded from
    its fifth frame): start_shape = "registered" moves the fit's start onto the recording's frame 0 and keeps the
    held corners, and the handles, where the scene holds them."""
    launched = SMALL_SCENE.replace('material = "gray-interlock"', 'material = "gray-interlock"\nvel = [1.5, 0.0, 0.0]')
    (tmp_path / "launched.toml").write_text(launched.format(extra=""))
    truth_model = wc.load_scene(tmp_path / "launched.toml").finalize("cpu", requires_grad=True)
    frames = np.stack(E.TrajectoryFit.simulate_targets(truth_model, _truth(), steps=24, frame_stride=STRIDE,
                                                       dt=0.02))[4:]
    clouds = recordings.point_cloud_recording(frames, truth_model.triangles_np, points=600, noise=0.001, drop=0.0,
                                              rng=np.random.default_rng(3))
    recordings.write_point_clouds(tmp_path / "clouds", clouds, kind=".npy")
    errors, held_at = {}, {}
    for shape in ("scene", "registered"):
        path = tmp_path / f"{shape}.toml"
        path.write_text(SMALL_SCENE.format(extra=f'[estimate]\ntargets = "clouds"\nframe_stride = {STRIDE}\n'
                                           f'start_shape = "{shape}"\n'))
        model = E.EstimationTask.from_scene(path, device="cpu").fit.model
        start = model.particle_x0.numpy()
        errors[shape] = float(np.sqrt(np.mean(np.sum((start - frames[0]) ** 2, axis=1))))
        held = model.handle_particle.numpy()
        held_at[shape] = start[held]
        np.testing.assert_allclose(model.handle_rest_target, start[held], atol=1e-6)
    np.testing.assert_array_equal(held_at["registered"], held_at["scene"])
    assert errors["scene"] > 0.03 and errors["registered"] < 0.01, errors


def test_a_registered_start_needs_a_point_cloud_recording(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text(SMALL_SCENE.format(extra='[estimate]\nstart_shape = "registered"\n'))
    with pytest.raises(ValueError, match="estimate.start_shape: 'registered' places the cloth on frame 0"):
        wc.load_scene(path)
