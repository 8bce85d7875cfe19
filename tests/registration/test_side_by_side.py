"""Estimates side by side on threads, taken in the order a loop takes them (registration.side_by_side)."""

import os
import threading
import time

import pytest

from apose_studio.registration import side_by_side
from apose_studio.registration.side_by_side import in_order


@pytest.fixture
def two_cpus(monkeypatch):
    monkeypatch.setattr(side_by_side, "usable_cpus", lambda: 2)


def test_results_come_in_the_items_order_though_later_ones_finish_first(two_cpus):
    def slow_first(i):
        time.sleep(0.05 * (4 - i))  # item 0 takes longest
        return i * i

    with in_order(slow_first, [0, 1, 2, 3], threads=2) as results:
        assert list(results) == [0, 1, 4, 9]


def test_the_work_runs_on_two_threads_at_once(two_cpus):
    inside, most = [0], [0]
    lock = threading.Lock()

    def work(i):
        with lock:
            inside[0] += 1
            most[0] = max(most[0], inside[0])
        time.sleep(0.05)
        with lock:
            inside[0] -= 1
        return i

    with in_order(work, range(4), threads=2) as results:
        assert list(results) == [0, 1, 2, 3]
    assert most[0] == 2


def test_the_first_item_is_computed_alone_in_the_callers_thread(two_cpus):
    """The first reading settles a frame most often: nothing is computed beside it until the caller asks for more."""
    calls = []

    def work(i):
        calls.append((i, threading.current_thread() is threading.main_thread()))
        time.sleep(0.02)
        return i

    with in_order(work, [0, 1, 2], threads=2) as results:
        assert next(results) == 0
        time.sleep(0.05)
        assert calls == [(0, True)]
        assert list(results) == [1, 2]
    assert sorted(calls[1:]) == [(1, False), (2, False)]


def test_leaving_early_cancels_what_has_not_started_and_waits_for_what_has(two_cpus):
    started, finished = set(), set()

    def work(i):
        started.add(i)
        time.sleep({0: 0.0, 1: 0.05}.get(i, 0.3))  # the others still running when the caller has item 1
        finished.add(i)
        return i

    with in_order(work, range(8), threads=2) as results:
        for r in results:
            if r == 1:
                break  # found what it looked for
    assert finished == started  # nothing runs on after the call
    assert len(started) <= 4  # item 0 alone; then 1, the one beside it, and at most the one its worker took next


def test_an_error_is_raised_where_its_item_is_reached(two_cpus):
    def work(i):
        if i == 1:
            raise ValueError("item 1")
        return i

    seen = []
    with pytest.raises(ValueError, match="item 1"):
        with in_order(work, [0, 1, 2], threads=2) as results:
            for r in results:
                seen.append(r)
    assert seen == [0]


def test_one_thread_or_one_cpu_runs_in_the_callers_thread_one_item_at_a_time(monkeypatch):
    calls = []

    def work(i):
        calls.append((i, threading.current_thread() is threading.main_thread()))
        return i

    with in_order(work, [0, 1, 2], threads=1) as results:
        assert next(results) == 0
        assert calls == [(0, True)]  # nothing computed ahead
    monkeypatch.setattr(side_by_side, "usable_cpus", lambda: 1)
    with in_order(work, [5, 6], threads=8) as results:
        assert list(results) == [5, 6]
    assert all(main for _, main in calls)


def test_work_computed_ahead_stops_at_its_next_check_once_the_caller_has_left(two_cpus):
    """A reading computed ahead of the one that settled the frame would run on for as long as it takes, and the
    caller would wait for it: it stops at its next `check` (each ICP step, each ray cast) instead."""
    stopped = []

    def work(i):
        if i < 2:
            return i
        for _ in range(1000):  # 10 s unless stopped
            side_by_side.check()
            time.sleep(0.01)
        return i

    def abandoned(i):
        try:
            return work(i)
        except side_by_side.Abandoned:
            stopped.append(i)
            raise

    t = time.perf_counter()
    with in_order(abandoned, [0, 1, 2, 3], threads=2) as results:
        assert next(results) == 0 and next(results) == 1
        time.sleep(0.05)  # items 2 and 3 running ahead
    assert time.perf_counter() - t < 2.0
    assert sorted(stopped) == [2, 3]
    side_by_side.check()  # outside a worker: nothing to stop


def test_a_frame_s_readings_computed_ahead_stop_inside_the_estimate(two_cpus, monkeypatch):
    """The estimate's own loops call `check`: an ICP run in a worker whose call has ended raises Abandoned."""
    import numpy as np

    from apose_studio.registration.solvers import icp_point_to_plane

    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.05, 0.05, (500, 3))
    normals = np.tile([0.0, 0.0, 1.0], (500, 1))
    stop = threading.Event()
    stop.set()
    monkeypatch.setattr(side_by_side._WORKER, "stop", stop, raising=False)
    with pytest.raises(side_by_side.Abandoned):
        icp_point_to_plane(pts, pts, normals, np.eye(4), 0.01, 10)
    monkeypatch.setattr(side_by_side._WORKER, "stop", None)
    assert np.allclose(icp_point_to_plane(pts, pts, normals, np.eye(4), 0.01, 10), np.eye(4))


def test_a_worker_reads_files_only_where_its_caller_may(two_cpus, tmp_path):
    """The studio confines every page action's file reads to its workspace (a thread-local setting): work handed to
    a worker thread is confined alike, or a path into the readers there would read anywhere."""
    from apose_studio import safeio
    from apose_studio.errors import AposeError

    inside, outside = tmp_path / "workspace", tmp_path / "elsewhere"
    inside.mkdir()
    outside.mkdir()
    (inside / "a.txt").write_text("a")
    (outside / "b.txt").write_text("b")

    in_workers = []

    def read(path):
        in_workers.append(threading.current_thread() is not threading.main_thread())
        fd, _ = safeio.open_regular(path)
        os.close(fd)
        return path.name

    a, b = inside / "a.txt", outside / "b.txt"
    with safeio.reads_within([inside]):
        with in_order(read, [a, a, a], threads=2) as results:
            assert list(results) == ["a.txt"] * 3
        with pytest.raises(AposeError, match="outside the studio's workspace"):
            with in_order(read, [a, a, b], threads=2) as results:  # the outside file read in a worker
                list(results)
    assert in_workers[1:3] == [True, True] and in_workers[4:6] == [True, True]
    with in_order(read, [b, b, b], threads=2) as results:  # no confinement: anywhere
        assert list(results) == ["b.txt"] * 3
