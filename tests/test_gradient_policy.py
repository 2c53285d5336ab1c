"""warpcloth.solver.gradients: the one decision of how a rollout's gradient is taken, and the graph cache that the
control tasks, the estimation fits and the torch bridge share."""

from __future__ import annotations

import math

import pytest

import warpcloth as wc
from warpcloth.solver.gradients import (
    CAPTURED_SEGMENTS_PARTICLE_STEPS,
    WHOLE_TAPE_PARTICLE_STEPS,
    GraphCache,
    default_segment_steps,
    plan_gradient,
)


def _sim(res: int = 4, **options) -> wc.Simulator:
    builder = wc.ModelBuilder(gravity=(0.0, 0.0, -9.8))
    builder.add_cloth_grid((res, res), (0.2, 0.2), material=wc.preset("gray-interlock"))
    builder.add_handle(0)
    return wc.Simulator(builder.finalize("cpu", requires_grad=True), dt=0.02, options=wc.SolverOptions(**options))


def test_a_small_rollout_is_taped_whole_and_a_large_one_checkpointed():
    assert default_segment_steps(100, WHOLE_TAPE_PARTICLE_STEPS // 100) == WHOLE_TAPE_PARTICLE_STEPS // 100
    steps = WHOLE_TAPE_PARTICLE_STEPS // 100 + 1
    assert default_segment_steps(100, steps) == math.ceil(math.sqrt(steps))


def test_the_plan_names_each_mode_and_why_a_rollout_is_not_captured():
    sim = _sim()  # 25 particles
    assert plan_gradient(sim, 30).mode == "captured"
    assert plan_gradient(sim, 30, segment_steps=6).mode == "captured-segments"
    off = plan_gradient(sim, 30, capture=False)
    assert off.mode == "whole" and off.uncaptured_because == "capture is off"
    assert plan_gradient(sim, 30, segment_steps=6, capture=False).mode == "checkpointed"
    long = CAPTURED_SEGMENTS_PARTICLE_STEPS // 25 + 1
    big = plan_gradient(sim, long)
    assert big.mode == "checkpointed" and big.segment_steps == math.ceil(math.sqrt(long))
    assert "CAPTURED_SEGMENTS_PARTICLE_STEPS" in big.uncaptured_because
    assert plan_gradient(sim, long, backward=False).captured  # a forward pass alone keeps no tape


def test_a_simulator_that_cannot_be_captured_runs_uncaptured_saying_why():
    sim = _sim(cg_backend="warp")
    plan = plan_gradient(sim, 10, backward=False)
    assert not plan.captured and plan.uncaptured_because == wc.CapturedRollout.unsupported(sim)


class _Capture:
    def __init__(self, name):
        self.name, self.fresh = name, True

    def current(self):
        return self.fresh


def test_the_cache_captures_at_the_after_th_ask_and_replays_later_asks():
    cache = GraphCache(after=3)
    made = []

    def make():
        made.append(_Capture(len(made)))
        return made[-1]

    assert cache.get("a", make) is None and cache.get("a", make) is None
    first = cache.get("a", make)
    assert first is made[0] and cache.get("a", make) is first and cache.made == 1
    first.fresh = False  # options or arrays replaced: made again at once
    second = cache.get("a", make)
    assert second is made[1] and second is not first and cache.made == 2


def test_the_cache_keeps_its_size_dropping_the_least_recently_used():
    cache = GraphCache(after=1, size=2)
    for key in ("a", "b", "a", "c"):  # "b" is the least recently used when "c" comes
        cache.get(key, lambda k=key: _Capture(k))
    assert cache.peek("b") is None and cache.peek("a").name == "a" and len(cache) == 2
    counts = GraphCache(after=2, size=1)
    counts.get("x", lambda: _Capture("x"))
    counts.get("y", lambda: _Capture("y"))  # forgets that "x" was asked
    assert counts.get("x", lambda: _Capture("x")) is None


@pytest.mark.parametrize("after, size", [(0, None), (2.0, None), (True, None), (2, 0)])
def test_the_cache_refuses_bad_settings(after, size):
    with pytest.raises(ValueError, match="GraphCache"):
        GraphCache(after=after, size=size)
