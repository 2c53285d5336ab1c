"""Many jobs at once (warpcloth.tasks.jobs): in this process and on a local Ray instance of 2 CPUs; the CLI's
multi-job JSON. Small grids, few steps and evaluations: the Ray tests start Ray once (a few seconds)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from warpcloth.cli import main
from warpcloth.tasks import estimation as E
from warpcloth.tasks.jobs import ControlJob, EstimateJob, JobResult, JobsInterrupted, RolloutJob, run_jobs, run_one

FIT = dict(steps=4, iters=3)  # the hanging cloth: 4 steps, 3 evaluations per fit


def _fits():
    return [EstimateJob(material="gray-interlock", **FIT), EstimateJob(target="/no/such/sequence", **FIT),
            EstimateJob(material="11oz-black-denim", **FIT)]


def _same_figures(a: JobResult, b: JobResult) -> None:
    """Equal records, bitwise, but for wall times."""
    assert a.ok and b.ok, (a.error, b.error)
    timing = {"runtime_s_per_step_iter", "seconds"}
    keys = set(a.result) - timing
    assert keys == set(b.result) - timing
    for k in keys:
        if isinstance(a.result[k], np.ndarray):
            np.testing.assert_array_equal(a.result[k], b.result[k])
        else:
            assert a.result[k] == b.result[k], k


def test_importing_warpcloth_imports_no_ray():
    code = "import sys, warpcloth, warpcloth.tasks.jobs, warpcloth.cli; print('ray' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_in_process_jobs_keep_order_and_a_failure_does_not_stop_the_others():
    results = run_jobs(_fits(), workers=1)
    assert [r.job for r in results] == _fits()
    assert results[0].ok and results[2].ok
    assert not results[1].ok and "/no/such/sequence" in results[1].error and results[1].result is None
    # a job's record is what its task gives when run directly
    task = _fits()[0].task()
    direct = task.run(optimizer=task.optimizer, iters=FIT["iters"])
    assert results[0].result["losses"] == direct.losses
    assert results[0].result["sim_err_pct"] == direct.simulation_error_pct
    assert results[0].seconds > 0
    # gray-interlock and 11oz fits differ (the jobs are not the same job twice)
    assert results[0].result["losses"] != results[2].result["losses"]


class _Interrupting:
    """A job that stands for Ctrl-C while it runs."""

    def run(self):
        raise KeyboardInterrupt

    def label(self):
        return "interrupting"


def test_ctrl_c_keeps_the_jobs_that_finished():
    jobs = [RolloutJob(steps=2), _Interrupting(), RolloutJob(steps=3)]
    with pytest.raises(JobsInterrupted) as info:
        run_jobs(jobs, workers=1)
    results = info.value.results
    assert results[0].ok and results[0].result["steps"] == 2
    assert results[1].error == "interrupted" and results[2].error == "interrupted"


def test_bad_workers_and_missing_ray_are_named(monkeypatch):
    with pytest.raises(ValueError, match="workers"):
        run_jobs([RolloutJob(steps=1)], workers=0)
    assert run_jobs([], workers=2) == []  # nothing to run: no Ray started
    monkeypatch.setitem(sys.modules, "ray", None)  # as if Ray were not installed
    with pytest.raises(ImportError, match=r"warpcloth\[ray\]"):
        run_jobs([RolloutJob(steps=1)], workers=2)
    assert main(["estimate", "--steps", "2", "--iters", "1", "--workers", "2"]) == 2
    # one worker needs no Ray
    assert run_jobs([RolloutJob(steps=1)], workers=1)[0].ok


def test_estimate_starts_fits_from_varied_bending_and_names_the_fit_of_least_loss(tmp_path, capsys):
    """--starts 3: three jobs from the task's start with its bending times 1, 1/2 and 2, in one JSON that names the
    one of least loss; the factors go on 1/4, 4; a bad count or start is refused, and so is a varied start for a fit
    that does not free the bending."""
    path = tmp_path / "starts.json"
    assert main(["estimate", "--steps", "4", "--iters", "3", "--starts", "3", "--json", str(path)]) == 0
    record = json.loads(path.read_text())
    results = record["results"]
    assert [r["job"]["start"] for r in results] == [0, 1, 2]
    bending = [np.asarray(r["estimate"]["bending"]) for r in results]
    assert not np.array_equal(bending[0], bending[1]) and not np.array_equal(bending[1], bending[2])
    losses = [r["best_loss"] for r in results]
    (label, index), = record["least"].items()
    assert index == int(np.argmin(losses)) and "start" not in label
    out = capsys.readouterr().out
    assert f"least loss of {label}'s 3 starts" in out and f"{label}, start 1 (bending x0.5)" in out
    start = EstimateJob(steps=4).task().start
    for k, factor in enumerate((1.0, 0.5, 2.0, 0.25, 4.0)):
        varied = E.varied_start(start, k)
        np.testing.assert_array_equal(varied.bending, start.bending * factor)
        assert varied.density == start.density and np.array_equal(varied.stretching, start.stretching)
    assert EstimateJob(steps=4, start=2).task().start.bending[0, 0] == 2.0 * start.bending[0, 0]
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="a start is numbered 0, 1, 2"):
            E.varied_start(start, bad)
    assert main(["estimate", "--steps", "2", "--iters", "1", "--starts", "0"]) == 2
    assert "--starts must be >= 1, got 0" in capsys.readouterr().err
    with pytest.raises(ValueError, match="start 1 varies the bending, which this fit does not free"):
        EstimateJob(steps=4, free=("density",), start=1).task()
    assert EstimateJob(steps=4, free=("density",), start=0).task().start.name == start.name
    assert main(["estimate", "--steps", "2", "--iters", "1", "--starts", "2", "--free", "density"]) == 2
    assert "varies the bending, which this fit does not free" in capsys.readouterr().err


def test_control_jobs_start_from_zero_or_seeded_random_pushes():
    zero, seeded = ControlJob(steps=10, iters=2), ControlJob(steps=10, iters=2, seed=3)
    task = zero.task()
    assert task.name == "basket-throw"
    assert zero.start(task) == {}
    expected = np.random.default_rng(3).normal(scale=5.0, size=task.n_params)
    np.testing.assert_array_equal(seeded.start(task)["start"], expected)
    a, b = run_one(zero), run_one(seeded)
    assert a.ok and b.ok and a.result["losses"] != b.result["losses"]
    assert a.result["scene"] == "basket-throw" and a.result["seed"] is None and b.result["seed"] == 3


# -- on Ray ---------------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def ray_instance():
    ray = pytest.importorskip("ray", reason="the ray extra is not installed (pip install -e '.[dev,ray]')")
    ray.init(num_cpus=2, include_dashboard=False, logging_level="ERROR", log_to_driver=False)
    yield ray
    ray.shutdown()


class _Dying:
    """A job whose worker process dies."""

    def run(self):
        os._exit(3)

    def label(self):
        return "dying"


def test_ray_results_equal_the_in_process_run(ray_instance):
    jobs = _fits() + [RolloutJob(steps=3)]
    here = run_jobs(jobs, workers=1)
    there = run_jobs(jobs, workers=2)
    assert [r.job for r in there] == jobs
    for a, b in zip(here, there):
        if a.ok:
            _same_figures(a, b)
        else:
            assert a.error == b.error
    assert ray_instance.is_initialized()  # an instance the caller started is left running


def test_a_worker_that_dies_fails_its_job_only(ray_instance):
    ray_instance.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the test's classes, to the workers
    jobs = [RolloutJob(steps=2), _Dying(), RolloutJob(steps=2), RolloutJob(steps=3)]
    results = run_jobs(jobs, workers=2)
    assert not results[1].ok and "worker died" in results[1].error
    assert all(results[k].ok for k in (0, 2, 3))
    np.testing.assert_array_equal(results[0].result["final_positions"], results[2].result["final_positions"])


def test_cli_gathers_one_json_of_every_job(ray_instance, tmp_path):
    path = tmp_path / "fits.json"
    status = main(["estimate", "--material", "gray-interlock", "--material", "11oz-black-denim", "--steps", "4",
                   "--iters", "3", "--workers", "2", "--json", str(path)])
    assert status == 0
    record = json.loads(path.read_text())
    assert record["workers"] == 2 and not record["interrupted"]
    assert [r["job"]["material"] for r in record["results"]] == ["gray-interlock", "11oz-black-denim"]
    single = tmp_path / "single.json"
    assert main(["estimate", "--material", "11oz-black-denim", "--steps", "4", "--iters", "3",
                 "--json", str(single)]) == 0
    one = json.loads(single.read_text())
    assert set(one) <= set(record["results"][1])  # the keys a single --json writes, and the job's settings
    assert record["results"][1]["losses"] == one["losses"]

    bad = tmp_path / "bad.json"
    status = main(["estimate", "--target", "/no/such/sequence", "--target",
                   "/no/such/other", "--workers", "2", "--json", str(bad)])
    assert status == 1  # some failed
    errors = [r["error"] for r in json.loads(bad.read_text())["results"]]
    assert "/no/such/sequence" in errors[0] and "/no/such/other" in errors[1]


CTRL_C_SCRIPT = '''
import json, pathlib, sys, time
from warpcloth.tasks.jobs import JobsInterrupted, RolloutJob, run_jobs

class Sleeper:
    def __init__(self, flag):
        self.flag = flag

    def run(self):
        pathlib.Path(self.flag).touch()  # tells the test this job is running
        time.sleep(120)
        return {}

    def label(self):
        return "sleeper"

try:
    run_jobs([RolloutJob(steps=2), Sleeper(sys.argv[1])], workers=2)
except JobsInterrupted as exc:
    print(json.dumps([r.error for r in exc.results]))
    sys.exit(130)
'''


def test_ctrl_c_on_ray_stops_the_workers_and_keeps_what_finished(tmp_path):
    pytest.importorskip("ray", reason="the ray extra is not installed (pip install -e '.[dev,ray]')")
    import signal
    import time

    script, started = tmp_path / "ctrl_c.py", tmp_path / "started"
    script.write_text(CTRL_C_SCRIPT)
    proc = subprocess.Popen([sys.executable, str(script), str(started)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # as in a terminal
    deadline = time.monotonic() + 120
    while not started.exists() and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.2)
    assert started.exists(), proc.communicate()[1][-2000:]
    time.sleep(5)  # the two-step rollout on the other worker finishes meanwhile
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)  # not the sleeper's 120 s: its worker is stopped
    assert proc.returncode == 130, err[-2000:]
    assert json.loads(out.strip().splitlines()[-1]) == [None, "interrupted"]
