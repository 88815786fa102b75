"""The fixed-step scheduler with an injected clock and an injected work timer."""
import pytest

from fsw.scheduler import Scheduler, Task


class FakeTimer:
    """Work timer that advances by a scripted cost each time a task runs."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def test_task_rates_follow_the_table():
    calls = {"fast": [], "slow": [], "hb": []}
    tasks = [Task("fast", lambda t: calls["fast"].append(t), 100, 1e-3),
             Task("slow", lambda t: calls["slow"].append(t), 10, 1e-3),
             Task("hb", lambda t: calls["hb"].append(t), 1, 1e-3)]
    s = Scheduler(100, tasks)
    for k in range(200):
        s.tick(k / 100)
    assert len(calls["fast"]) == 200
    assert calls["slow"] == pytest.approx([k / 10 for k in range(20)])
    assert calls["hb"] == pytest.approx([0.0, 1.0])
    assert s.stats.ticks == 200


def test_overruns_counted_per_tick_and_per_task():
    timer = FakeTimer()

    def cost(seconds):
        def fn(_t):
            timer.now += seconds
        return fn

    tasks = [Task("sensor", cost(0.004), 50, budget_s=0.005),
             Task("estimator", cost(0.012), 25, budget_s=0.010)]
    s = Scheduler(50, tasks, work_timer=timer)   # period 20 ms
    for k in range(10):
        s.tick(k * 0.02)
    # estimator runs on even ticks: 12 ms > 10 ms budget, tick work 16 ms < 20 ms period
    assert s.task("estimator").overruns == 5
    assert s.task("sensor").overruns == 0
    assert s.stats.overruns == 0
    s.task("sensor").fn = cost(0.010)
    s.tick(0.2)  # 10 + 12 = 22 ms > 20 ms
    assert s.stats.overruns == 1
    mean, p50, p99, mx = s.stats.summary_us()
    assert mx == pytest.approx(22_000)
    assert p50 == pytest.approx(16_000)


def test_bad_rates_rejected():
    with pytest.raises(ValueError):
        Scheduler(0, [])
    with pytest.raises(ValueError):
        Scheduler(10, [Task("x", lambda t: None, 20, 1e-3)])


def test_run_histogram_percentiles_match_numpy_to_a_microsecond():
    import numpy as np

    from fsw.runner import WorkHistogram

    work_s = np.random.default_rng(4).lognormal(np.log(30e-6), 0.8, 20_000)
    h = WorkHistogram()
    for w in work_s:
        h.add(float(w))
    for p in (50, 99):
        assert abs(h.percentile_us(p) - np.percentile(work_s * 1e6, p)) <= 1.0
    assert h.mean_us() == pytest.approx(work_s.mean() * 1e6)
    assert h.max_s == work_s.max()


def test_catch_up_passes_run_the_pipeline_while_samples_wait_and_the_budget_has_room():
    """A backlog of 5 samples, a pipeline pass of 2 ms, a 10 ms period and a 75 % budget: the ordinary pass
    and two catch-up passes fit (2 + 2 + 2 + the 1 ms task = 7 ms), a third would not; the cost per sample
    is measured from the passes, and the every-tick task outside the pipeline runs once."""
    timer = FakeTimer()
    backlog = [5]
    runs = {"poll": 0, "pipe": 0}

    def poll(_t):
        runs["poll"] += 1
        timer.now += 0.001

    def pipe(_t):
        runs["pipe"] += 1
        backlog[0] -= 1
        timer.now += 0.002

    s = Scheduler(100, [Task("poll", poll, 100, 1e-3), Task("pipe", pipe, 100, 5e-3, per_sample=True)],
                  work_timer=timer, backlog=lambda: backlog[0], taken=lambda: True, sample_budget=0.75)
    work = s.tick(0.0)
    assert runs == {"poll": 1, "pipe": 3} and backlog[0] == 2
    assert s.stats.catch_up_passes == 2 and s.stats.samples == 3
    assert s.stats.sample_cost_s == pytest.approx(0.002) and work == pytest.approx(0.007)
    assert s.stats.overruns == 0
    s.tick(0.01)
    assert backlog[0] == 0 and runs["pipe"] == 5   # the rest, and no pass on an empty queue


def test_a_pipeline_that_declines_ends_the_catch_up():
    timer = FakeTimer()
    s = Scheduler(100, [Task("pipe", lambda t: None, 100, 5e-3, per_sample=True)], work_timer=timer,
                  backlog=lambda: 3, taken=lambda: False)
    s.tick(0.0)
    assert s.stats.catch_up_passes == 1 and s.stats.samples == 0
