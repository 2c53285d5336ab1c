"""Several optimisations in lockstep, each in its own thread, their requests answered as one batch (one simulation
of several worlds) once every unfinished one has asked, in the order of the runs: no result depends on timing."""

from __future__ import annotations

import threading
from collections.abc import Callable


class Lockstep:
    """Requests of ``runs`` optimisations, answered by ``evaluate(requests) -> answers`` (dicts keyed by run, in run
    order) once every run still going has asked, then ``on_batch()``; an exception of ``evaluate`` answers them all."""

    def __init__(self, runs: int, evaluate: Callable[[dict], dict], on_batch: Callable[[], None] | None = None):
        self.running = runs
        self.evaluate = evaluate
        self.on_batch = on_batch
        self.pending: dict[int, object] = {}
        self.answers: dict[int, object] = {}
        self.lock = threading.Condition()

    def ask(self, run: int, request):
        """``run``'s answer to ``request``, from the next batch (blocking until it ran); an exception answer raises."""
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
        """A run is done: the others no longer wait for it."""
        with self.lock:
            self.running -= 1
            self._dispatch()

    def _dispatch(self) -> None:
        # (holding the lock) evaluate the requests once every unfinished run has made one
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
    """``body(run)`` of every run, each in its own thread that leaves ``lockstep`` at its end: the results in order,
    an exception in its run's place."""
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
