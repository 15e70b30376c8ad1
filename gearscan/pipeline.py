"""Threaded stages joined by bounded queues (DESIGN.md, "Data flow, live").

Each stage runs in its own thread. A full queue drops its OLDEST item and counts it, so a
slow stage never blocks acquisition. A stage that raises stops the whole pipeline, and
:meth:`Pipeline.run` raises :class:`PipelineError` naming the stage. Stop requests (Ctrl-C,
SIGTERM, a burst or time limit) let the items in flight drain, then every stage's
``close`` runs (the recorder finalises, the viewer flushes).
"""

from __future__ import annotations

import collections
import logging
import signal
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

log = logging.getLogger(__name__)

_END = object()  # end-of-stream marker, passed down the chain


class PipelineError(RuntimeError):
    """A stage failed; ``stage`` names it and ``__cause__`` holds its exception."""

    def __init__(self, stage: str, error: BaseException):
        super().__init__(f"stage {stage!r} failed: {type(error).__name__}: {error}")
        self.stage = stage
        self.report: PipelineReport | None = None  # the counters up to the failure (set by run())


class DropOldestQueue:
    """Bounded FIFO whose ``put`` never blocks: when full, the oldest item is dropped and counted."""

    def __init__(self, maxsize: int, name: str = "queue") -> None:
        if maxsize < 1:
            raise ValueError(f"{name}: maxsize must be >= 1, got {maxsize}")
        self.name = name
        self.maxsize = maxsize
        self._items: collections.deque = collections.deque()
        self._cv = threading.Condition()
        self.dropped = 0

    def put(self, item: Any) -> None:
        with self._cv:
            if item is not _END:
                while len(self._items) >= self.maxsize:
                    old = self._items.popleft()
                    if old is _END:  # never drop the end marker
                        self._items.appendleft(old)
                        break
                    self.dropped += 1
            self._items.append(item)
            self._cv.notify()

    def get(self, timeout: float | None = None) -> Any:
        """Next item; raises TimeoutError after ``timeout`` s without one."""
        with self._cv:
            if not self._cv.wait_for(lambda: self._items, timeout=timeout):
                raise TimeoutError(f"{self.name}: no item within {timeout} s")
            return self._items.popleft()

    def __len__(self) -> int:
        with self._cv:
            return len(self._items)


@dataclass
class StageStats:
    """Counters and timings of one stage (latency = time spent in the stage's function)."""

    name: str
    processed: int = 0
    emitted: int = 0
    dropped_in: int = 0
    latencies_ms: collections.deque = field(default_factory=lambda: collections.deque(maxlen=256))
    started: float = field(default_factory=time.perf_counter)

    def as_dict(self) -> dict[str, float]:
        lat = np.array(self.latencies_ms) if self.latencies_ms else np.zeros(1)
        elapsed = max(time.perf_counter() - self.started, 1e-9)
        return {
            "processed": self.processed,
            "emitted": self.emitted,
            "dropped_in": self.dropped_in,
            "latency_ms_mean": float(lat.mean()),
            "latency_ms_p95": float(np.percentile(lat, 95)),
            "throughput_per_s": self.emitted / elapsed,
        }


@dataclass
class StageSpec:
    """A stage: ``fn(item) -> output | None`` (None emits nothing); ``close`` runs at shutdown.

    ``workers`` > 1 runs ``fn`` on that many items at once (``fn`` must be thread-safe); the
    outputs still leave in input order.
    """

    name: str
    fn: Callable[[Any], Any]
    close: Callable[[], None] | None = None
    queue_size: int = 4
    workers: int = 1

    def __post_init__(self) -> None:
        if self.workers < 1:
            raise ValueError(f"stage {self.name!r}: workers must be >= 1, got {self.workers}")


class _InOrder:
    """Tickets taken with each input and a reorder buffer, so parallel workers emit in input order."""

    def __init__(self, workers: int) -> None:
        self.take = threading.Lock()  # held across get + ticket: tickets follow queue order
        self.lock = threading.Lock()
        self.next_ticket = 0
        self.next_out = 0
        self.done: dict[int, Any] = {}
        self.alive = workers

    def ticket(self) -> int:
        t, self.next_ticket = self.next_ticket, self.next_ticket + 1
        return t

    def finish(self, ticket: int, result: Any) -> list[Any]:
        """Store ``ticket``'s result; the results now due, in order (None: nothing to emit).

        Call with ``lock`` held, and emit the results before releasing it: two workers emitting
        outside the lock could still swap their outputs.
        """
        self.done[ticket] = result
        due = []
        while self.next_out in self.done:
            due.append(self.done.pop(self.next_out))
            self.next_out += 1
        return due

    def retire(self) -> bool:
        """One worker stops; True for the last one (it closes the stage)."""
        with self.lock:
            self.alive -= 1
            return self.alive == 0


@dataclass
class PipelineReport:
    stages: dict[str, dict[str, float]]
    wall_s: float
    stopped_by: str

    def summary(self) -> str:
        rows = [f"{n}: {s['emitted']:.0f} out, {s['dropped_in']:.0f} dropped, "
                f"{s['latency_ms_mean']:.1f} ms mean / {s['latency_ms_p95']:.1f} ms p95"
                for n, s in self.stages.items()]
        return f"{self.wall_s:.1f} s, stopped by {self.stopped_by}\n  " + "\n  ".join(rows)


class Pipeline:
    """``source`` (an iterable of items, run in its own thread) followed by ``stages``."""

    def __init__(self, source: Iterable[Any] | Callable[[], Iterator[Any]], stages: list[StageSpec],
                 *, source_name: str = "source", source_close: Callable[[], None] | None = None,
                 on_stats: Callable[[dict[str, dict[str, float]]], None] | None = None,
                 blas_threads: int | None = 1) -> None:
        self._source = source
        # The stages already run in parallel; a multi-threaded BLAS (numpy's OpenBLAS) spins its
        # own pool on the same cores as torch's and the other stages. One BLAS thread measured
        # 479 -> 345 core-ms per 512x512 burst, 4.05 -> 5.10 bursts/s on a quiet host
        # (benchmarks/pipeline_report.md); None leaves BLAS alone.
        self.blas_threads = blas_threads
        self._source_name = source_name
        self._source_close = source_close
        self.specs = stages
        self.queues = [DropOldestQueue(s.queue_size, f"{s.name} input") for s in stages]
        self.stats = {source_name: StageStats(source_name), **{s.name: StageStats(s.name) for s in stages}}
        self._stop = threading.Event()
        self._error: PipelineError | None = None
        self._error_lock = threading.Lock()
        self.stopped_by = "end of input"
        self.on_stats = on_stats

    # --- control ------------------------------------------------------------------
    def stop(self, reason: str = "stop requested") -> None:
        if not self._stop.is_set():
            self.stopped_by = reason
            self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def _fail(self, stage: str, exc: BaseException) -> None:
        # The first error is raised by run() and printed once by whoever called it; logging it
        # here as well printed every CLI error twice. Later ones (often consequences) are logged.
        with self._error_lock:
            if self._error is None:
                self._error = PipelineError(stage, exc)
                self._error.__cause__ = exc
                log.debug("%s", self._error)
            else:
                log.warning("also failed after the first error: stage %r: %s: %s", stage, type(exc).__name__, exc)
        self.stop(f"error in {stage}")

    # --- threads --------------------------------------------------------------------
    def _run_source(self) -> None:
        st = self.stats[self._source_name]
        out = self.queues[0] if self.queues else None
        it = None
        try:
            it = self._source() if callable(self._source) else iter(self._source)
            while not self._stop.is_set():
                t0 = time.perf_counter()
                try:
                    item = next(it)
                except StopIteration:
                    break
                st.latencies_ms.append((time.perf_counter() - t0) * 1e3)
                st.processed += 1
                st.emitted += 1
                if out is not None:
                    out.put(item)
        except BaseException as exc:  # noqa: BLE001 - reported through PipelineError
            self._fail(self._source_name, exc)
        finally:
            # a generator source runs its own cleanup (e.g. a `with` block) when closed
            self._close(self._source_name, getattr(it, "close", None), self._source_close)
            if out is not None:
                out.put(_END)

    def _close(self, name: str, *closers: Callable[[], None] | None) -> None:
        """Run each cleanup; a failing one is reported as that stage's error, the rest still run."""
        for fn in closers:
            if fn is None:
                continue
            try:
                fn()
            except Exception as exc:  # noqa: BLE001 - reported through PipelineError
                self._fail(name, exc)

    def _run_stage(self, k: int, order: _InOrder) -> None:
        spec, inq = self.specs[k], self.queues[k]
        outq = self.queues[k + 1] if k + 1 < len(self.queues) else None
        st = self.stats[spec.name]
        try:
            while True:
                with order.take:
                    try:
                        item = inq.get(timeout=0.1)
                    except TimeoutError:
                        if self._error is not None:
                            break
                        continue
                    if item is _END:
                        inq.put(_END)  # the stage's other workers stop on it too
                        break
                    ticket = order.ticket()
                result = None
                if self._error is None:  # after a failure elsewhere: drain without work
                    t0 = time.perf_counter()
                    result = spec.fn(item)
                    st.latencies_ms.append((time.perf_counter() - t0) * 1e3)
                with order.lock:  # DropOldestQueue.put never blocks
                    st.processed += 1
                    st.dropped_in = inq.dropped
                    for out in order.finish(ticket, result):
                        if out is not None:
                            st.emitted += 1
                            if outq is not None:
                                outq.put(out)
        except BaseException as exc:  # noqa: BLE001 - reported through PipelineError
            self._fail(spec.name, exc)
        finally:
            if order.retire():
                st.dropped_in = inq.dropped
                self._close(spec.name, spec.close)
                if outq is not None:
                    outq.put(_END)

    def run(self, *, duration: float | None = None, handle_signals: bool = True) -> PipelineReport:
        """Run until the source ends, ``duration`` passes, :meth:`stop`, Ctrl-C or SIGTERM."""
        t_start = time.perf_counter()
        previous = {}
        if handle_signals and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                previous[sig] = signal.signal(sig, lambda s, f: self.stop(signal.Signals(s).name))
        threads = [threading.Thread(target=self._run_source, name=self._source_name, daemon=True)]
        for k, spec in enumerate(self.specs):
            order = _InOrder(spec.workers)
            threads += [threading.Thread(target=self._run_stage, args=(k, order), daemon=True,
                                         name=spec.name if spec.workers == 1 else f"{spec.name}-{w}")
                        for w in range(spec.workers)]
        blas = threadpool_limits(self.blas_threads, user_api="blas") if self.blas_threads else None
        try:
            for t in threads:
                t.start()
            while any(t.is_alive() for t in threads):
                threads[-1].join(timeout=0.2)
                if duration is not None and time.perf_counter() - t_start > duration:
                    self.stop("duration reached")
                if self.on_stats:
                    self.on_stats({n: s.as_dict() for n, s in self.stats.items()})
        finally:
            self.stop(self.stopped_by)
            for t in threads:
                t.join(timeout=30)
            for sig, handler in previous.items():
                signal.signal(sig, handler)
            if blas is not None:
                blas.restore_original_limits()
        report = PipelineReport({n: s.as_dict() for n, s in self.stats.items()}, time.perf_counter() - t_start, self.stopped_by)
        if self._error is not None:
            self._error.report = report
            raise self._error
        return report
