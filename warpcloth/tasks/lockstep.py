"""Several optimisations run in lockstep: each in its own thread, their requests answered as one batch (one
simulation of several worlds) once every optimisation still running waits for its own answer.

The batch is handed the requests keyed and ordered by run, so what it simulates, and so every result, does not
depend on the threads' timing: each run's result is the one it gets alone wherever a batch of worlds gives each
world what it gives alone (tests/test_worlds.py). Control's restarts (``optimize_open_loop_starts``) and material
fits of many worlds (``estimate_materials``) use it.
"""

from __future__ import annotations

import threading
from collections.abc import Callable


class Lockstep:
    """Requests of ``runs`` optimisations, answered by ``evaluate(requests) -> answers`` (dicts keyed by run, the
    requests in the runs' order) once every run still going has asked; ``on_batch()`` after each batch (a progress
    bar). An exception that ``evaluate`` raises is every waiting run's answer, so none waits forever."""

    def __init__(self, runs: int, evaluate: Callable[[dict], dict], on_batch: Callable[[], None] | None = None):
        self.running = runs
        self.evaluate = evaluate
        self.on_batch = on_batch
        self.pending: dict[int, object] = {}
        self.answers: dict[int, object] = {}
        self.lock = threading.Condition()

    def ask(self, run: int, request):
        """Run ``run``'s ``request`` with the others' (blocks until the batch ran); its answer, or raises the
        exception that is its answer."""
        with self.lock:
            self.pending[run] = request
            self._dispatch()
            while run not in self.answers:
                self.lock.wait()
            answer = self.answers.pop(run)
        if isinstance(answer, BaseException):
            raise answer
        return answer

    def leave(self) -> None:
        """Run ``run`` is done: the others no longer wait for it."""
        with self.lock:
            self.running -= 1
            self._dispatch()

    def _dispatch(self) -> None:
        """(Holding the lock.) Evaluate the requests once every unfinished run has made one."""
        if not self.pending or len(self.pending) < self.running:
            return
        requests = dict(sorted(self.pending.items()))
        self.pending = {}
        try:
            self.answers.update(self.evaluate(requests))
        except BaseException as exc:  # noqa: BLE001 -- every waiting run gets it
            self.answers.update(dict.fromkeys(requests, exc))
        if self.on_batch is not None:
            self.on_batch()
        self.lock.notify_all()


def run_in_lockstep(lockstep: Lockstep, runs: int, body: Callable[[int], object]) -> list:
    """``body(run)`` for every run, each in its own thread (leaving ``lockstep`` when it returns or raises);
    returns their results in order, or the exceptions they raised in their place."""
    results: list = [None] * runs

    def one(run: int) -> None:
        try:
            results[run] = body(run)
        except BaseException as exc:  # noqa: BLE001 -- handed to the caller
            results[run] = exc
        finally:
            lockstep.leave()

    threads = [threading.Thread(target=one, args=(run,), name=f"lockstep run {run}", daemon=True)
               for run in range(runs)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return results
