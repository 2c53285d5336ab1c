"""Issue 38's tools against what they claim. The Gaussian-smoothed gradient (tasks/optim.py smoothed_gradient) is
the gradient of the smoothed loss: exactly where it is known in closed form (a quadratic; a jump), and against
central differences of the smoothed loss, estimated with the same perturbations, through a simulation run as
worlds of one batch. CMA-ES (tasks/optim.py cmaes) converges on an ill-conditioned quadratic and leaves a basin
that holds gradient descent; its generations run as forward-only batches (ControlTask.losses_worlds), bitwise the
full evaluations' losses."""

from importlib import resources
from types import SimpleNamespace

import numpy as np
import pytest
import warp as wp

import warpcloth as wc
from warpcloth.cli import main
from warpcloth.scene import load_scene
from warpcloth.tasks import estimation as E
from warpcloth.tasks import scenes as S
from warpcloth.tasks import throw as C
from warpcloth.tasks.controllers import optimize_open_loop, train_mlp
from warpcloth.tasks.optim import cmaes, smoothed_gradient
from warpcloth.tasks.specs import SearchSpec


def evaluator(loss, grad):
    """An evaluate_many over a NumPy loss and its (pointwise) gradient."""
    return lambda requests: [SimpleNamespace(loss=loss(p), grad=grad(p)) for p, _ in requests]


def test_a_quadratics_smoothed_gradient_is_its_gradient():
    # for L = |A p|^2 / 2 smoothing adds a constant: both estimators are unbiased, the first order exact
    A = np.random.default_rng(1).standard_normal((4, 3))
    p = np.array([0.3, -1.0, 2.0])
    exact = A.T @ A @ p
    evaluate = evaluator(lambda q: 0.5 * float(np.sum((A @ q) ** 2)), lambda q: A.T @ A @ q)
    first = smoothed_gradient(evaluate, p, scale=0.5, samples=8, rng=np.random.default_rng(0))
    np.testing.assert_allclose(first.grad, exact, rtol=1e-12)
    zeroth = smoothed_gradient(evaluate, p, scale=0.5, samples=40000, rng=np.random.default_rng(0), zeroth_order=True)
    np.testing.assert_allclose(zeroth.grad, exact, atol=0.05 * np.abs(exact).max())  # Monte Carlo: ~1 % here


def test_across_a_jump_only_the_zeroth_order_estimate_sees_the_smoothed_slope():
    # L = 1 where p0 > 0: the pointwise gradient is 0 everywhere it exists, the smoothed loss is Phi(p0 / s), whose
    # slope at 0 is phi(0) / s: what a landing or a strike on a rim does to a throw's loss, in one dimension
    s = 0.2
    evaluate = evaluator(lambda q: float(q[0] > 0.0), lambda q: np.zeros(3))
    p = np.zeros(3)
    zeroth = smoothed_gradient(evaluate, p, scale=s, samples=20000, rng=np.random.default_rng(2), zeroth_order=True)
    slope = 1.0 / np.sqrt(2.0 * np.pi) / s
    assert zeroth.grad[0] == pytest.approx(slope, rel=0.03)
    assert np.abs(zeroth.grad[1:]).max() < 0.05 * slope
    first = smoothed_gradient(evaluate, p, scale=s, samples=20, rng=np.random.default_rng(2))
    assert np.all(first.grad == 0.0)  # the tape's gradients miss the jump


def test_the_smoothed_gradient_of_a_simulation_matches_central_differences_of_the_smoothed_loss():
    # four steps of the throw (in the air, no contact), float64; 6 copies run as 6 worlds of one model, bitwise the
    # copies run one by one
    task = C.ThrowTask(S.basket_scene("cpu", dtype=wp.float64), steps=4)
    p = np.random.default_rng(3).normal(scale=2.0, size=task.n_params)
    scale, samples = 0.5, 6

    def smoothed_at(q):
        return smoothed_gradient(task.evaluate_many, q, scale=scale, samples=samples, rng=np.random.default_rng(4))

    at = smoothed_at(p)
    assert at.samples == samples and at.failed == 0 and task.batches >= 1
    d = np.random.default_rng(5).standard_normal(task.n_params)
    h = 1e-4
    fd = (smoothed_at(p + h * d).loss - smoothed_at(p - h * d).loss) / (2 * h)  # the same perturbations
    assert abs(fd) > 1e-8
    assert at.grad @ d == pytest.approx(fd, rel=1e-5)
    # the batch evaluated the perturbed copies: the mean of their gradients, each simulated alone (the flying
    # throw's loss is nearly quadratic in its pushes, so the smoothed gradient is close to the one at p itself:
    # that comparison could not tell the points apart)
    eps = np.random.default_rng(4).standard_normal((samples // 2, task.n_params))
    alone = [task.evaluate(p + scale * e).grad for e in np.concatenate([eps, -eps])]
    np.testing.assert_array_equal(at.grad, np.mean(alone, axis=0))


def test_bad_arguments_are_refused():
    evaluate = evaluator(lambda q: 0.0, lambda q: np.zeros(1))
    with pytest.raises(ValueError, match="even integer"):
        smoothed_gradient(evaluate, np.zeros(1), scale=1.0, samples=3, rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="scale must be finite"):
        smoothed_gradient(evaluate, np.zeros(1), scale=0.0, samples=2, rng=np.random.default_rng(0))


def test_cmaes_converges_on_a_quadratic():
    A = np.random.default_rng(6).standard_normal((10, 10)) + 3.0 * np.eye(10)

    def losses(points):
        return [0.5 * float(np.sum((A @ (x - 1.0)) ** 2)) for x in points]

    # condition number ~2000: measured 1e-5 after 200 generations, 8e-12 after 300
    best = cmaes(losses, np.zeros(10), sigma=1.0, generations=300, rng=np.random.default_rng(0))
    assert losses([best])[0] < 1e-8


def test_cmaes_leaves_the_basin_that_holds_a_gradient_method():
    # Rastrigin in 2-D from (3, -3), inside a local basin: gradient descent stays there, CMA-ES finds the origin
    def rastrigin(x):
        return 20.0 + float(np.sum(x * x - 10.0 * np.cos(2.0 * np.pi * x)))

    def grad(x):
        return 2.0 * x + 20.0 * np.pi * np.sin(2.0 * np.pi * x)

    x = np.array([3.0, -3.0])
    for _ in range(500):
        x = x - 1e-3 * grad(x)
    assert rastrigin(x) > 15.0  # a local minimum near (3, -3)
    # a population of 60: 5 seeds of 5 reach the origin in 100 generations (24: 3 of 5, the others a neighbour)
    best = cmaes(lambda points: [rastrigin(p) for p in points], np.array([3.0, -3.0]), sigma=3.0, popsize=60,
                 generations=100, rng=np.random.default_rng(1))
    assert rastrigin(best) < 1e-6, best


def test_forward_only_batched_losses_equal_the_full_evaluations():
    # what CMA-ES's generations run: the losses and final positions of evaluate_worlds, bitwise, without the tape
    task = C.ThrowTask(S.basket_scene("cpu", dtype=wp.float64), steps=30)
    points = [np.random.default_rng(k).normal(scale=2.0, size=task.n_params) for k in range(3)]
    batch = task.worlds(3)
    fast, full = batch.losses_worlds(points), batch.evaluate_worlds(points)
    for a, b in zip(fast, full):
        assert a.loss == b.loss and a.grad is None
        np.testing.assert_array_equal(a.positions, b.positions)
    assert task.losses_worlds([points[1]])[0].loss == fast[1].loss  # a world alone, bitwise


def test_the_global_search_counts_every_trial_and_refines_from_its_best_point():
    # 20 steps of the throw in float64: two generations of 4 points (forward only, one batch of worlds each), then
    # Gauss-Newton from the best of them with the 6 simulations left
    task = C.ThrowTask(S.basket_scene("cpu", dtype=wp.float64), steps=20)
    seen = []
    search = SearchSpec(population=4, sigma=3.0, refine=6, seed=5)
    result = optimize_open_loop(task, iters=14, optimizer="cmaes", search=search,
                                callback=lambda k, loss, err, params: seen.append((loss, np.array(params))))
    assert len(result.losses) == 14 and not result.failed_trials
    searched = seen[:8]
    # each trial's loss is the full evaluation's, bitwise (the population ran as worlds, forward only)
    assert task.evaluate(searched[3][1]).loss == searched[3][0]
    best = min(range(8), key=lambda k: result.errors_pct[k])
    # the local stage starts at the search's best point and only improves on it
    np.testing.assert_array_equal(seen[8][1], searched[best][1])
    assert result.error_pct <= result.errors_pct[best]
    assert result.error_pct == min(result.errors_pct)
    with pytest.raises(ValueError, match="cmaes: 14 simulations, 6 of them left to the local optimiser, make no "
                                         "generation of 10 points"):
        optimize_open_loop(task, iters=14, optimizer="cmaes", search=SearchSpec(population=10, refine=6))
    # the same seed, the same search
    again = optimize_open_loop(task, iters=8, optimizer="cmaes", search=SearchSpec(population=4, sigma=3.0, refine=0,
                                                                                     seed=5))
    assert again.losses == result.losses[:8]


def test_the_smoothed_search_follows_the_mean_gradient_of_its_copies_and_refines_from_its_best_point():
    # 20 steps of the throw in float64: two Adam steps on the smoothed loss, each from 4 perturbed copies (two
    # antithetic pairs, one batch of worlds, each a simulation), then Gauss-Newton from the best copy
    task = C.ThrowTask(S.basket_scene("cpu", dtype=wp.float64), steps=20)
    seen = []
    sigma = 2.0
    result = optimize_open_loop(task, iters=14, optimizer="smoothed", search=SearchSpec(population=4, sigma=sigma,
                                                                                        refine=6, seed=1),
                                callback=lambda k, loss, err, params: seen.append((loss, np.array(params))))
    assert len(result.losses) == 14 and not result.failed_trials
    copies = seen[:8]
    np.testing.assert_allclose(copies[0][1] + copies[2][1], 0.0, atol=1e-12)  # antithetic around zero pushes
    assert task.evaluate(copies[1][1]).loss == copies[1][0]  # each copy's loss is its own simulation's
    # Adam's first step moves every push by its step, sigma (controllers.SMOOTHED_STEP_FRACTION is
    # 1), against the mean gradient of the copies
    grad = np.mean([task.evaluate(p).grad for _, p in copies[:4]], axis=0)
    centre = 0.5 * (copies[4][1] + copies[6][1])
    np.testing.assert_allclose(centre, -sigma * np.sign(grad), rtol=1e-9)
    best = min(range(8), key=lambda k: result.errors_pct[k])
    np.testing.assert_array_equal(seen[8][1], copies[best][1])  # the local stage starts at the best copy
    assert result.error_pct == min(result.errors_pct)
    for search, message in [(SearchSpec(population=3), r"search\.population must be even"),
                            (SearchSpec(population=10, refine=6), "14 simulations, 6 of them left to the local "
                                                                  "optimiser, make no step of 10 copies")]:
        with pytest.raises(ValueError, match=f"smoothed: {message}"):
            optimize_open_loop(task, iters=14, optimizer="smoothed", search=search)


def test_the_multistart_interleaves_its_runs_and_keeps_the_best():
    # three Gauss-Newton runs of 4 simulations in lockstep, from zero and two random starts: each as it runs alone
    task = C.ThrowTask(S.basket_scene("cpu", dtype=wp.float64), steps=20)
    seen = []
    result = optimize_open_loop(task, iters=12, optimizer="multistart", search=SearchSpec(population=3, sigma=3.0,
                                                                                          seed=2),
                                callback=lambda k, loss, err, params: seen.append((k, loss, err)))
    rng = np.random.default_rng(2)
    starts = [np.zeros(task.n_params)] + [rng.normal(scale=3.0, size=task.n_params) for _ in range(2)]
    alone = [optimize_open_loop(task, iters=4, start=s) for s in starts]
    assert result.losses == [run.losses[k] for k in range(4) for run in alone]
    assert result.error_pct == min(run.error_pct for run in alone)
    assert result.errors_pct[result.simulations - 1] == result.error_pct
    assert min(result.errors_pct[:result.simulations - 1]) > result.error_pct  # the first time it was reached
    assert seen and all(result.losses[k - 1] == loss and result.errors_pct[k - 1] == err for k, loss, err in seen)
    with pytest.raises(ValueError, match="multistart: 2 simulations for 3 starts"):
        optimize_open_loop(task, iters=2, optimizer="multistart", search=SearchSpec(population=3))


def test_a_warm_started_mlp_starts_where_the_open_loop_ended():
    # whatever its random weights, the network fitted to the open loop's pushes repeats their simulation
    pytest.importorskip("torch")
    task = C.ThrowTask(S.basket_scene("cpu", dtype=wp.float64), steps=150)
    opened = optimize_open_loop(task, iters=5)
    for seed in (1, 2):
        result = train_mlp(task, iters=7, warm_start=5, seed=seed, zero_start=False, optimizer="gauss-newton")
        assert result.errors_pct[:5] == opened.errors_pct
        # the open loop's best pushes simulated through the torch bridge (the CG's tolerance, 1e-6, apart from the
        # task's own simulation), then the network's first simulation: those pushes again, to the pinv's rounding
        assert result.errors_pct[5] == pytest.approx(opened.error_pct, rel=1e-4)
        assert result.errors_pct[6] == pytest.approx(result.errors_pct[5], rel=1e-9)
        assert len(result.errors_pct) == 7 and result.error_pct <= opened.error_pct + 1e-9
    with pytest.raises(ValueError, match="warm_start"):
        train_mlp(task, iters=5, warm_start=5)


def test_search_settings_in_a_scene_and_on_the_command_line(tmp_path, capsys):
    scenes = resources.files("warpcloth.scenes")
    throw = scenes.joinpath("basket-throw.toml").read_text().replace("meshes/", f"{scenes.joinpath('meshes')}/")

    def load(old: str, new: str):
        path = tmp_path / "s.toml"
        path.write_text(throw.replace(old, new))
        return load_scene(path).control

    gn = 'optimizer = "gauss-newton"\n'
    spec = load(gn, 'optimizer = "cmaes"\nsearch = { population = 6, sigma = 2.5, refine = 10, seed = 3 }\n')
    assert spec.optimizer == "cmaes" and spec.search == SearchSpec(population=6, sigma=2.5, refine=10, seed=3)
    assert load(gn, 'optimizer = "cmaes"\n').search == SearchSpec()
    assert load(gn, 'optimizer = "multistart"\nsearch = { population = 4, seed = 2 }\n').search == SearchSpec(
        population=4, seed=2)
    for new, message in [('search = { population = 6 }\n', r"control\.search: .*multistart or cmaes.*'gauss-newton'"),
                         ('optimizer = "multistart"\nsearch = { refine = 5 }\n', r"control\.search.*refine"),
                         ('optimizer = "multistart"\nsearch = { population = 51 }\n',
                          r"control\.search\.population: 51 starts"),
                         ('optimizer = "cmaes"\nsearch = { refine = 50 }\n', r"control\.search\.refine: .*nothing"),
                         ('optimizer = "cmaes"\nsearch = { popsize = 6 }\n', r"control\.search.*popsize"),
                         ('optimizer = "cmaes"\nsearch = { population = 1 }\n', r"control\.search\.population"),
                         ('warm_start = 10\n', r"control\.warm_start: .*MLP")]:
        with pytest.raises(ValueError, match=message):
            load(gn, new)
    mlp = 'controller = "mlp"\noptimizer = "gauss-newton"\n'
    assert load('controller = "open-loop"\n' + gn, mlp + 'warm_start = 20\n').warm_start == 20
    with pytest.raises(ValueError, match=r"control\.warm_start: .*nothing"):
        load('controller = "open-loop"\n' + gn, mlp + 'warm_start = 50\n')
    # the command line refuses what the controller cannot run, before any simulation
    assert main(["control", "--optimizer", "adam", "--iters", "1"]) == 2
    assert "--optimizer: unknown value 'adam'" in capsys.readouterr().err
    assert main(["control", "--warm-start", "5", "--controller", "open-loop"]) == 2
    assert "--warm-start 5: the MLP controller's" in capsys.readouterr().err
    assert main(["control", "--warm-start", "5"]) == 2  # the scene's controller is the open loop
    assert "this run's controller: open-loop" in capsys.readouterr().err


def small_fit(template: bool = False) -> E.TrajectoryFit:
    """A 3x3 hanging cloth in the wind, 6 steps, float64, its targets simulated with tango-red-jet-set (with its
    builder as the fit's ``template`` where asked)."""
    truth = wc.preset("tango-red-jet-set", thicken=2)
    b = wc.ModelBuilder()
    b.add_cloth_grid((3, 3), (0.3, 0.3), material=wc.preset("gray-interlock", thicken=2), rot=S.GRID_TO_YZ,
                     pos=(0.0, -0.15, -0.15), vel=(0.5, 0.0, 0.0))
    b.add_handle(12)
    b.add_handle(15)
    b.set_wind((3.0, 0.0, 0.0))
    model = b.finalize("cpu", requires_grad=True, dtype=wp.float64)
    options = wc.SolverOptions(cg_tol=1e-12, warm_start=False)
    return E.TrajectoryFit(model, E.TrajectoryFit.simulate_targets(model, truth, steps=6), steps=6, options=options,
                           template=b if template else None)


def test_a_material_fits_global_search_counts_its_forward_evaluations_and_ends_with_lbfgs():
    # two generations of 4 materials (forward only), then 4 L-BFGS evaluations
    fit = small_fit()
    search = SearchSpec(population=4, sigma=0.5, refine=4, seed=1)
    result = E.estimate_material(fit, optimizer="cmaes", iters=12, scan=None, search=search)
    assert len(result.losses) == 12 and not result.diverged
    searched = result.losses[:8]
    # L-BFGS starts from the search's best material and only accepts a decrease
    assert result.losses[8] == min(searched)
    assert fit.loss(result.material) <= min(searched)
    assert fit.loss(result.material) < 0.5 * fit.loss(E.initial_guess())
    before = fit.evaluations, fit.seconds  # the forward losses add to seconds, the gradients to both
    with pytest.raises(ValueError, match="cmaes: 12 evaluations, 4 of them left to L-BFGS, make no generation of 9"):
        E.estimate_material(fit, optimizer="cmaes", iters=12, scan=None, search=SearchSpec(population=9, refine=4))
    assert (fit.evaluations, fit.seconds) == before  # refused before any simulation


def test_a_materials_smoothed_search_follows_the_mean_gradient_of_its_copies_and_refines_from_its_best_point():
    # two Adam steps on the smoothed loss, each from 4 perturbed materials (two antithetic pairs), then L-BFGS from
    # the best of them: every material is the one the search's random numbers say, every loss its own simulation's
    fit = small_fit()
    sigma, n = 0.1, E.N_PARAMS
    result = E.estimate_material(fit, optimizer="smoothed", iters=12, scan=None,
                                 search=SearchSpec(population=4, sigma=sigma, refine=4, seed=3))
    assert len(result.losses) == 12 and not result.diverged
    param = E.MaterialParameterization(E.initial_guess())
    rng = np.random.default_rng(3)
    eps = rng.standard_normal((2, n))
    first = [sigma * e for e in np.concatenate([eps, -eps])]
    evaluations = [fit.loss_and_grad(param.decode(theta)) for theta in first]
    assert [e[0] for e in evaluations] == result.losses[:4]
    grad = np.mean([param.chain(theta, *e[1:]) for theta, e in zip(first, evaluations)], axis=0)
    centre = -sigma / 4 * grad / (np.abs(grad) + 1e-12)  # Adam's first step: sigma / 4 against the mean gradient
    eps = rng.standard_normal((2, n))
    second = [centre + sigma * e for e in np.concatenate([eps, -eps])]
    np.testing.assert_allclose([fit.loss(param.decode(theta)) for theta in second], result.losses[4:8], rtol=1e-12)
    assert result.losses[8] == min(result.losses[:8])  # L-BFGS starts at the best copy and only accepts a decrease
    assert fit.loss(result.material) == min(result.losses)
    for search, message in [(SearchSpec(population=3), r"search\.population must be even"),
                            (SearchSpec(population=10, refine=4), "12 evaluations, 4 of them left to L-BFGS, make "
                                                                  "no step of 10 copies")]:
        with pytest.raises(ValueError, match=f"smoothed: {message}"):
            E.estimate_material(fit, optimizer="smoothed", iters=12, scan=None, search=search)


def test_a_materials_multistart_runs_lbfgs_from_each_start_and_keeps_the_best():
    # three L-BFGS runs of 3 evaluations, one after another: from the start, then from two random points around it
    fit = small_fit()
    result = E.estimate_material(fit, optimizer="multistart", iters=9, scan=None,
                                 search=SearchSpec(population=3, sigma=0.3, seed=4))
    assert len(result.losses) == 9 and not result.diverged
    assert result.losses[:3] == E.estimate_material(fit, optimizer="lbfgs", iters=3, scan=None).losses
    param = E.MaterialParameterization(E.initial_guess())
    rng = np.random.default_rng(4)
    starts = [rng.normal(0.0, 0.3, E.N_PARAMS) for _ in range(2)]
    assert [result.losses[3], result.losses[6]] == [fit.loss(param.decode(s)) for s in starts]
    assert fit.loss(result.material) == min(result.losses)
    with pytest.raises(ValueError, match="multistart: 3 starts for 2 evaluations"):
        E.estimate_material(fit, optimizer="multistart", iters=2, scan=None, search=SearchSpec(population=3))


@pytest.mark.parametrize("optimizer", ["cmaes", "smoothed", "multistart"])
def test_a_materials_global_search_runs_its_trials_as_worlds_of_one_batch(optimizer):
    # the same search as one evaluation after another: each trial's loss and the material found, bitwise (the
    # default solver: the batch's gives each world its own multigrid), its trials simulated as worlds of the fit's
    # copies
    search = SearchSpec(population=4, sigma=0.3, refine=4, seed=2)
    results, fits = [], []
    for batch in (False, True):
        fits.append(small_fit(template=True))
        results.append(E.estimate_material(fits[-1], optimizer=optimizer, iters=14, scan=None, search=search,
                                           batch=batch))
    one_by_one, batched = results
    assert len(batched.losses) == 14 and not batched.diverged
    if optimizer == "multistart":
        # in lockstep: each round the evaluations of the runs still going (shares 5, 3, 3, 3: the last two rounds
        # are the first run's alone, a batch of one world)
        shares, first = [5, 3, 3, 3], [0, 5, 8, 11]
        order = [(run, r) for r in range(5) for run in range(4) if r < shares[run]]
        assert batched.losses == [one_by_one.losses[first[run] + r] for run, r in order]
        assert fits[1].worlds(1).seconds > 0.0
    else:
        assert batched.losses == one_by_one.losses
    for part in ("density", "stretching", "bending"):
        np.testing.assert_array_equal(getattr(batched.material, part), getattr(one_by_one.material, part))
    copies = fits[1].worlds(4)
    assert copies.sim.linear_solver.preconditioner == fits[1].sim.linear_solver.preconditioner == "multigrid"
    assert copies.world_count == 4 and copies.seconds > 0.0 and fits[0].worlds(4).seconds == 0.0
    assert batched.seconds >= copies.seconds


def test_a_batch_is_refused_where_there_is_nothing_to_batch_or_nothing_to_batch_on():
    fit = small_fit()  # no template: no copies to run trials on
    with pytest.raises(ValueError, match=r"batch=True needs a TrajectoryFit .* template=builder"):
        E.estimate_material(fit, optimizer="smoothed", iters=12, scan=None, batch=True)
    with pytest.raises(ValueError, match="batch=True simulates a global search's trials .*; lbfgs has none"):
        E.estimate_material(small_fit(template=True), optimizer="lbfgs", iters=12, scan=None, batch=True)
    assert fit.evaluations == 0 and fit.seconds == 0.0  # refused before any simulation
    with pytest.raises(ValueError, match="count must be a positive integer, got 0"):
        small_fit(template=True).worlds(0)
    other = wc.ModelBuilder()
    other.add_cloth_grid((2, 2), (0.3, 0.3), material=wc.preset("gray-interlock", thicken=2))
    with pytest.raises(ValueError, match="the template has 1 world.* of 9 particles in all; it must be the one-world "
                                         r"builder the model \(1 world\(s\), 16 particles\)"):
        E.TrajectoryFit(fit.model, [np.zeros((16, 3))] * 4, steps=6, template=other)
