"""The farm's scheduling and sizing policies and shard assembly alone: no Ray, a fake clock, made-up
workers."""

from __future__ import annotations

import pytest

from farm.assembly import ShardAssembly
from farm.scheduler import Scheduler
from storage.schema import Layout


def sched(n: int = 6, **kw) -> Scheduler:
    kw = {"max_attempts": 3, "backoff_s": 10.0, "blocklist_after": 3, "timeout_s": 100.0} | kw
    return Scheduler(range(n), **kw)


def test_every_worker_gets_one_task_before_any_gets_a_second():
    s = sched(6)
    assert s.dispatch(["a", "b"], ["a", "b"], 0.0) == [("a", 0), ("b", 1), ("a", 2), ("b", 3)]
    assert s.running("a") == 0 and [x.task for x in s.assigned["a"]] == [0, 2]
    assert list(s.queue) == [4, 5]
    assert s.dispatch(["a", "b"], ["a", "b"], 1.0) == []  # both full


def test_no_second_task_when_the_queue_is_not_longer_than_the_workers():
    s = sched(2)
    assert s.dispatch(["a", "b", "c"], ["a", "b", "c"], 0.0) == [("a", 0), ("b", 1)]
    s = sched(3)
    assert s.dispatch(["a", "b"], ["a", "b"], 0.0) == [("a", 0), ("b", 1), ("a", 2)]


def test_no_second_task_while_a_starting_worker_could_take_it():
    s = sched(2)
    assert s.dispatch(["a"], ["a", "b"], 0.0) == [("a", 0)]  # b is starting: 1 waits for it
    assert s.dispatch(["a", "b"], ["a", "b"], 1.0) == [("b", 1)]
    s = sched(6)  # a long queue: the ready worker takes two while b starts
    assert s.dispatch(["a"], ["a", "b"], 0.0) == [("a", 0), ("a", 1)]


def test_a_failed_task_waits_its_backoff_then_goes_to_another_worker():
    s = sched(1)
    assert s.dispatch(["a", "b"], ["a", "b"], 0.0) == [("a", 0)]
    out = s.failed("a", 0, "RenderError: boom", 5.0)
    assert (out.final, out.blocklist, out.attempts) == (False, False, 1)
    assert s.dispatch(["a", "b"], ["a", "b"], 14.9) == []  # backoff 10 s from t = 5
    assert s.dispatch(["a", "b"], ["a", "b"], 15.1) == [("b", 0)]  # not a, which failed it
    s.failed("b", 0, "again", 16.0)
    assert s.not_before[0] == pytest.approx(36.0)  # 10 * 2**1
    # every known worker has failed it: any may retry it
    assert s.dispatch(["a"], ["a", "b"], 40.0) == [("a", 0)]
    out = s.failed("a", 0, "third", 41.0)
    assert out.final and s.final == {0: "third"} and s.finished
    assert [e["error"] for e in s.errors[0]] == ["RenderError: boom", "again", "third"]


def test_a_retry_waits_for_a_starting_worker_that_has_not_failed_it():
    s = sched(1)
    s.dispatch(["a"], ["a"], 0.0)
    s.failed("a", 0, "x", 0.0)
    assert s.dispatch(["a"], ["a", "b"], 100.0) == []  # b exists but is not placed yet
    assert s.dispatch(["a", "b"], ["a", "b"], 100.0) == [("b", 0)]


def test_idle_workers_take_no_retry_they_all_failed():
    s = sched(3)
    s.dispatch(["a", "b"], ["a", "b"], 0.0)  # a: 0, 2; b: 1
    s.completed("b", 1, 1.0)
    s.failed("a", 0, "x", 2.0)  # back at the queue's end, behind nothing: [0]
    assert list(s.queue) == [0]
    assert s.takers(["a"]) == 0  # a failed it (a still runs 2, but say it were idle)
    assert s.takers(["b"]) == 1
    assert s.takers(["a", "b"]) == 1  # one task: one taker
    s.queue.appendleft(7)  # a fresh task: a takes that, the retry is b's
    assert s.takers(["a"]) == 1 and s.takers(["a", "b"]) == 2
    assert s.takers([]) == 0


def test_a_retry_at_a_jobs_tail_starts_a_fresh_worker_and_waits_for_it():
    """The other worker was released at the tail; the one left failed the last task: it is
    not the retry's taker, so a fresh worker is started up to ``--workers 2`` and the retry
    waits for it (a backoff that ends before it comes does not hand it back)."""
    from farm.sizing import to_start

    s = sched(1)
    s.dispatch(["a"], ["a"], 0.0)
    s.failed("a", 0, "x", 1.0)
    more = to_start(fit=2, placed=1, starting=0, queued=len(s.queue), taken=s.takers(["a"]))
    assert more == 1
    assert s.dispatch(["a"], ["a", "c"], 50.0) == []  # c starting: a does not take it back
    assert s.dispatch(["a", "c"], ["a", "c"], 51.0) == [("c", 0)]
    # with no room for another (--workers 1), the worker left takes it
    s = sched(1)
    s.dispatch(["a"], ["a"], 0.0)
    s.failed("a", 0, "x", 1.0)
    assert to_start(fit=1, placed=1, starting=0, queued=1, taken=s.takers(["a"])) == 0
    assert s.dispatch(["a"], ["a"], 50.0) == [("a", 0)]


def test_a_retry_waits_for_a_starting_worker_for_a_bounded_time_only():
    """A fresh worker that Ray cannot place (another job took the room) is known, so waited
    for, for ``--retry-wait`` seconds; then the worker that failed the retry takes it."""
    from farm.scheduler import awaited

    assert awaited(["a"], {"c": 100.0}, 219.0, 120.0) == ["a", "c"]
    assert awaited(["a"], {"c": 100.0}, 220.0, 120.0) == ["a"]
    assert awaited(["a"], {"c": 100.0}, 100.0, 0.0) == ["a"]  # --retry-wait 0: never
    assert awaited([], {}, 0.0, 120.0) == []
    s = sched(1)
    s.dispatch(["a"], ["a"], 0.0)
    s.failed("a", 0, "x", 1.0)  # c is started for it at t = 1 and never placed
    assert s.dispatch(["a"], awaited(["a"], {"c": 1.0}, 60.0, 120.0), 60.0) == []
    assert s.dispatch(["a"], awaited(["a"], {"c": 1.0}, 121.0, 120.0), 121.0) == [("a", 0)]


def test_blocklist_after_a_workers_third_failure():
    s = sched(3, max_attempts=5)
    s.dispatch(["a"], ["a"], 0.0)
    outs = [s.failed("a", t, "x", 1.0) for t in (0, 1)]
    assert [o.blocklist for o in outs] == [False, False]
    s.dispatch(["a"], ["a"], 100.0)
    assert s.failed("a", s.running("a"), "x", 101.0).blocklist


def test_a_removed_worker_gives_back_its_waiting_tasks_uncounted_to_the_front():
    s = sched(5)
    s.dispatch(["a", "b"], ["a", "b"], 0.0)  # a: 0, 2; b: 1, 3
    assert s.remove_worker("a", keep=0) == [2]
    assert list(s.queue) == [2, 4] and s.attempts[2] == 0
    assert [x.task for x in s.assigned["a"]] == [0]  # to fail on its own
    s.failed("a", 0, "worker died", 1.0)
    assert s.assigned["a"] == [] and list(s.queue) == [2, 4, 0]
    assert s.remove_worker("b") == [1, 3] and list(s.queue) == [1, 3, 2, 4, 0]


def test_lost_results_go_back_to_the_front_uncounted_and_the_job_is_not_finished():
    s = sched(4)
    s.dispatch(["a"], ["a"], 0.0)  # a: 0, 1
    s.completed("a", 0, 1.0)
    s.completed("a", 1, 2.0)
    s.requeue([0, 1])  # their shard's commit found the results gone
    assert list(s.queue) == [0, 1, 2, 3] and s.attempts[0] == 0 and not s.finished


def test_timeouts_count_from_when_a_task_starts_running():
    s = sched(4, timeout_s=100.0)
    s.dispatch(["a", "b"], ["a", "b"], 0.0)  # a: 0 then 2; b: 1 then 3
    s.completed("a", 0, 90.0)  # 2 starts running at t = 90
    assert s.running("a") == 2 and s.started_at("a", 2) == 90.0
    assert s.expired(150.0) == [("b", 1)]  # b's first task ran since t = 0
    assert s.expired(160.0) == []  # reported once
    assert s.expired(191.0) == [("a", 2)]
    assert 1 in s.timed_out
    s.remove_worker("b", keep=1)
    s.failed("b", 1, "timed out", 200.0)
    assert 1 not in s.timed_out and s.attempts[1] == 1


def test_an_idle_worker_recalls_a_task_waiting_at_a_busy_one():
    s = sched(3)
    assert s.dispatch(["a"], ["a", "b"], 0.0) == [("a", 0), ("a", 1)]  # b starts late
    assert s.waiting() == 1  # 1 waits behind 0: b takes it if it comes up with nothing else
    assert s.dispatch(["a", "b"], ["a", "b"], 1.0) == [("b", 2)]
    assert s.recall(["a", "b"], ["a", "b"], 1.0) == []  # b is busy, a holds a running task
    s.completed("b", 2, 2.0)
    assert s.recall(["a", "b"], ["a", "b"], 2.0) == [("a", 1)]  # b idle, nothing queued
    assert list(s.queue) == [1] and s.running("a") == 0
    assert s.dispatch(["a", "b"], ["a", "b"], 2.0) == [("b", 1)]  # a is full: its mark counts
    assert s.recall(["a", "b"], ["a", "b"], 2.5) == []  # nothing waits anywhere now
    assert s.waiting() == 0  # a's mark of 1 is not a task that waits
    s.completed("b", 1, 3.0)
    s.completed("a", 0, 4.0)
    assert s.finished and s.only_marks() == ["a"]  # a's run of 1 is not waited for
    s.dropped("a", 1, 4.1)
    assert s.finished and s.attempts[1] == 0 and s.only_marks() == []


def test_a_recalled_task_run_all_the_same_is_dropped_and_its_hang_fails_nothing():
    s = sched(3, timeout_s=10.0)
    s.dispatch(["a", "b"], ["a", "b"], 0.0)  # a: 0, 2; b: 1
    s.completed("b", 1, 1.0)
    assert s.recall(["a", "b"], ["a", "b"], 1.0) == [("a", 2)]
    assert s.dispatch(["a", "b"], ["a", "b"], 1.0) == [("b", 2)]
    s.completed("a", 0, 2.0)  # a comes to 2 before the cancel: it runs there too
    assert s.running("a") is None and s.only_marks() == ["a"]
    s.requeue([0])  # a task to hand out (a lost result): not behind a's run of 2
    assert s.dispatch(["a", "b"], ["a", "b"], 2.0) == []  # b is busy with 2
    assert s.recall(["a", "b"], ["a", "b"], 2.0) == []  # and a is no taker either
    s.completed("b", 2, 5.0)
    assert s.dispatch(["a", "b"], ["a", "b"], 5.0) == [("b", 0)]
    s.completed("b", 0, 6.0)
    assert s.expired(13.0) == [("a", None)] and not s.timed_out  # a's run fails nothing
    s.dropped("a", 2, 13.5)
    assert s.finished and s.attempts[2] == 0


def test_no_recall_while_the_queue_has_work_or_for_a_worker_that_failed_the_task():
    s = sched(4)
    s.dispatch(["a", "b"], ["a", "b"], 0.0)  # a: 0, 2; b: 1, 3
    s.failed("b", 1, "boom", 1.0)  # 1 waits its backoff in the queue; b still holds 3
    s.completed("b", 3, 1.0)
    assert s.recall(["a", "b"], ["a", "b"], 1.0) == [("a", 2)]  # 1 cannot go before 11 s
    assert s.recall(["a", "b"], ["a", "b"], 1.5) == []  # the queue has 2 for b now
    s = sched(3)
    s.dispatch(["a", "b"], ["a", "b"], 0.0)  # a: 0, 2; b: 1
    s.completed("b", 1, 1.0)
    s.failed_on[2] = {"b"}  # as if b had failed 2 before
    assert s.recall(["a", "b"], ["a", "b"], 1.0) == []  # a has not failed it: it waits for a


def test_retries_waiting_their_backoff_do_not_keep_an_idle_worker_from_a_recall():
    s = sched(4)
    s.dispatch(["a", "b"], ["a", "b"], 0.0)  # a: 0, 2; b: 1, 3
    s.failed("b", 1, "boom", 1.0)  # due at 6 s
    s.failed("b", 3, "boom", 1.0)  # due at 6 s: as many queued as workers, none to go now
    assert s.recall(["a", "b"], ["a", "b"], 1.0) == [("a", 2)]
    assert list(s.queue) == [2, 1, 3] and s.dispatch(["a", "b"], ["a", "b"], 1.0) == [("b", 2)]
    s.completed("b", 2, 2.0)
    assert s.recall(["a", "b"], ["a", "b"], 2.0) == []  # nothing else waits behind a's 0


def test_a_removed_worker_gives_back_its_tasks_but_not_the_recalled_ones():
    s = sched(4)
    s.dispatch(["a", "b"], ["a", "b"], 0.0)  # a: 0, 2; b: 1, 3
    s.completed("b", 1, 1.0)
    s.completed("b", 3, 1.0)
    assert s.recall(["a", "b"], ["a", "b"], 1.0) == [("a", 2)]
    assert s.remove_worker("a") == [0] and list(s.queue) == [0, 2]
    assert s.assigned["a"] == []


def test_finished_only_when_nothing_is_queued_or_held():
    s = sched(1)
    assert not s.finished
    s.dispatch(["a"], ["a"], 0.0)
    assert not s.finished
    s.completed("a", 0, 1.0)
    assert s.finished


def test_shard_assembly_returns_a_whole_shard_in_material_order_and_drops_dead_ones():
    layout = Layout(num_materials=6, suns_per_material=2, resolution=16, shard_size=4)
    shards = ShardAssembly(layout)  # 2 materials a shard
    assert shards.add(1, {"m": 1}) is None
    assert shards.add(0, {"m": 0}) == (0, [{"m": 0}, {"m": 1}])
    assert shards.kill(3) == 1
    assert shards.add(2, {"m": 2}) is None and 1 not in shards.waiting
    assert shards.add(5, {"m": 5}) is None
    assert shards.waiting == {2: {5: {"m": 5}}}


def test_a_shards_surviving_results_wait_again_for_the_lost_ones_rendered_anew():
    layout = Layout(num_materials=6, suns_per_material=2, resolution=16, shard_size=6)
    shards = ShardAssembly(layout)  # 3 materials a shard; shard 0's commit lost material 1
    shards.keep(0, {0: {"m": 0}, 2: {"m": 2}})
    assert shards.add(1, {"m": "1 again"}) == (0, [{"m": 0}, {"m": "1 again"}, {"m": 2}])
    assert 0 not in shards.waiting


def test_a_job_is_sized_to_the_cluster_and_its_materials():
    from farm.sizing import initial, room

    assert room({"CPU": 64.0, "GPU": 8.0}, 4, 0) == 16
    assert room({"CPU": 64.0, "GPU": 8.0}, 4, 1) == 8  # the GPUs bound GPU workers
    assert room({"CPU": 64.0}, 1, 1) == 0  # no GPU yet
    assert room({"CPU": 0.0}, 1, 0) == 0  # a head with no CPUs
    assert room({"CPU": 7.0}, 2, 0) == 3
    assert room({"CPU": 9.0, "GPU": 2.0}, 4, 1) == 2
    assert initial(None, 16, 3) == 3  # no Blender for a material that is not there
    assert initial(None, 16, 40) == 16
    assert initial(None, 0, 40) == 1  # no room: one worker, which waits for a node
    assert initial(5, 16, 40) == 5  # --workers is what it says, beyond the room there is
    assert initial(5, 16, 3) == 3  # but starts no Blender (nor autoscaled node) for nothing


def test_a_job_grows_onto_what_the_cluster_gains_while_tasks_are_queued():
    from farm.sizing import to_start

    assert to_start(fit=8, placed=4, starting=0, queued=100) == 4  # a node of 4 CPUs joined
    assert to_start(fit=8, placed=4, starting=1, queued=100) == 0  # one still waits for room
    assert to_start(fit=8, placed=4, starting=0, queued=2) == 2  # the queue keeps 2 busy
    assert to_start(fit=8, placed=4, starting=0, queued=0) == 0  # the job's last tasks run
    assert to_start(fit=2, placed=4, starting=0, queued=100) == 0  # never shrinks
    assert to_start(fit=8, placed=4, starting=0, queued=3, taken=1) == 2  # one is the idle one's
    assert to_start(fit=8, placed=4, starting=0, queued=1, taken=1) == 0  # a retry's backoff


def test_workers_waiting_for_room_beyond_the_queue_are_given_up():
    from farm.sizing import surplus

    assert surplus(starting=3, queued=10) == 0  # each may yet get a task
    assert surplus(starting=3, queued=1) == 2  # the tail: one node asked for is enough
    assert surplus(starting=0, queued=0) == 0


def test_idle_workers_are_released_at_a_jobs_tail_only():
    from farm.sizing import release

    assert release(idle=3, queued=0, running=2) == 3  # the tail: their nodes can go
    assert release(idle=3, queued=1, running=2) == 0  # a queued task (or a retry's) is theirs
    assert release(idle=3, queued=0, running=0) == 0  # the job is ending: every one stops
    assert release(idle=0, queued=0, running=2) == 0
