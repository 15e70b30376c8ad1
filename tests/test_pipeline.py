"""Pipeline mechanics: drop-oldest queues, stage errors, clean shutdown."""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from gearscan.pipeline import DropOldestQueue, Pipeline, PipelineError, StageSpec


def test_queue_drops_oldest_and_counts():
    q = DropOldestQueue(3)
    for i in range(5):
        q.put(i)
    assert q.dropped == 2
    assert [q.get(0.1) for _ in range(3)] == [2, 3, 4]
    with pytest.raises(TimeoutError):
        q.get(0.01)


def test_items_flow_and_stats_count():
    out = []
    p = Pipeline(range(20), [StageSpec("double", lambda x: 2 * x, queue_size=100), StageSpec("sink", out.append, queue_size=100)])
    rep = p.run(handle_signals=False)
    assert out == [2 * i for i in range(20)]
    assert rep.stages["double"]["processed"] == 20 and rep.stopped_by == "end of input"


def test_slow_stage_drops_oldest_without_blocking_the_source():
    seen = []

    def slow(x):
        time.sleep(0.02)
        seen.append(x)

    p = Pipeline(range(200), [StageSpec("slow", slow, queue_size=2)])
    rep = p.run(handle_signals=False)
    assert rep.stages["slow"]["dropped_in"] > 100
    assert seen[-1] == 199  # the newest item always survives
    assert rep.stages["slow"]["dropped_in"] + len(seen) == 200


def test_failing_stage_is_named_and_closes_everything():
    closed = []

    def boom(x):
        if x == 5:
            raise ValueError("bad burst")
        return x

    def forever():
        i = 0
        while True:
            yield i
            i += 1
            time.sleep(0.001)

    p = Pipeline(forever, [StageSpec("infer", boom, close=lambda: closed.append("infer")),
                           StageSpec("record", lambda x: x, close=lambda: closed.append("record"))])
    with pytest.raises(PipelineError, match=r"stage 'infer' failed: ValueError: bad burst") as err:
        p.run(handle_signals=False)
    assert sorted(closed) == ["infer", "record"]
    # the counters up to the failure come with it (the live end summary prints them):
    # items 0..4 passed the failing stage, item 5 did not
    rep = err.value.report
    assert rep is not None and rep.stopped_by == "error in infer"
    assert rep.stages["record"]["processed"] == rep.stages["infer"]["processed"] == 5


def test_sigint_drains_and_finalises():
    closed = threading.Event()
    done = []

    def forever():
        i = 0
        while True:
            yield i
            i += 1
            time.sleep(0.002)

    p = Pipeline(forever, [StageSpec("record", done.append, close=closed.set)])
    before = signal.getsignal(signal.SIGINT)  # default_int_handler, or SIG_IGN under nohup / a background job
    threading.Timer(0.3, lambda: os.kill(os.getpid(), signal.SIGINT)).start()
    rep = p.run()
    assert rep.stopped_by == "SIGINT" and closed.is_set() and len(done) > 10
    # the previous handler is back (in a terminal: SIGINT raises KeyboardInterrupt again)
    assert signal.getsignal(signal.SIGINT) is before


def test_duration_limit():
    def forever():
        while True:
            time.sleep(0.005)
            yield 1

    rep = Pipeline(forever, [StageSpec("sink", lambda x: None)]).run(duration=0.2, handle_signals=False)
    assert rep.stopped_by == "duration reached" and rep.wall_s < 2


def test_blas_runs_single_threaded_inside_the_pipeline_and_is_restored():
    """Stages run in parallel already; numpy's BLAS pool must not spin on the same cores."""
    from threadpoolctl import threadpool_info

    def blas_threads() -> list[int]:
        return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]

    before = blas_threads()
    assert before, "numpy's BLAS not found by threadpoolctl"
    inside: list[list[int]] = []
    Pipeline(range(3), [StageSpec("probe", lambda _: inside.append(blas_threads()))]).run(handle_signals=False)
    assert inside and all(t == [1] * len(before) for t in inside)
    assert blas_threads() == before


def test_parallel_workers_overlap_and_emit_in_input_order():
    out, running, peak = [], [0], [0]
    lock = threading.Lock()

    def slow(x):
        with lock:
            running[0] += 1
            peak[0] = max(peak[0], running[0])
        time.sleep(0.03 if x % 3 == 0 else 0.005)  # later items often finish first
        with lock:
            running[0] -= 1
        return x

    closed = []
    p = Pipeline(range(30), [StageSpec("infer", slow, queue_size=100, workers=2, close=lambda: closed.append(1)),
                             StageSpec("sink", out.append, queue_size=100)])
    rep = p.run(handle_signals=False)
    assert out == list(range(30))
    assert peak[0] == 2 and closed == [1]  # two at once, closed once
    assert rep.stages["infer"]["processed"] == rep.stages["infer"]["emitted"] == 30


def test_failing_worker_of_a_parallel_stage_is_named():
    def boom(x):
        if x == 7:
            raise ValueError("bad burst")
        return x

    p = Pipeline(range(50), [StageSpec("infer", boom, workers=2, queue_size=100), StageSpec("sink", lambda x: None)])
    with pytest.raises(PipelineError, match=r"stage 'infer' failed: ValueError: bad burst"):
        p.run(handle_signals=False)
    with pytest.raises(ValueError, match="workers must be >= 1"):
        StageSpec("infer", boom, workers=0)
