"""ThreadGovernor: the thread count a training uses is the one measured fastest, re-measured."""

from __future__ import annotations

import pytest

from neural_estimator.training.threads import ThreadGovernor


class FakeMachine:
    """A clock and a thread setting; a step at n threads takes step_seconds[n] of the clock."""

    def __init__(self, step_seconds: dict[int, float]) -> None:
        self.now, self.threads, self.step_seconds, self.sets = 0.0, None, dict(step_seconds), []

    def set_threads(self, n: int) -> None:
        self.threads = n
        self.sets.append(n)

    def clock(self) -> float:
        return self.now

    def train(self, gov: ThreadGovernor, steps: int) -> list[int]:
        used = []
        for _ in range(steps):
            gov.before_step()
            used.append(self.threads)
            self.now += self.step_seconds[self.threads]
            gov.after_step()
        return used


def governor(machine: FakeMachine, max_threads: int = 2, **kw) -> ThreadGovernor:
    return ThreadGovernor(max_threads, set_threads=machine.set_threads, clock=machine.clock, **kw)


def test_a_busy_machine_trains_on_one_thread_after_the_probe():
    m = FakeMachine({1: 0.10, 2: 0.30})  # two threads 3x slower: the other core is busy
    gov = governor(m, probe_steps=4, period=100.0)
    used = m.train(gov, 60)
    # one thread: an untimed step after the switch, then 4 timed; two threads: the untimed step
    # and one timed step, 3x the best so far, which ends the probe there
    probe = (1 + 4) + (1 + 1)
    assert used[:probe] == [1] * 5 + [2, 2]
    assert set(used[probe:]) == {1}
    assert gov.decisions[0]["chose"] == 1 and gov.decisions[0]["ms"] == {"1": 100.0, "2": 300.0}


def test_a_count_only_somewhat_slower_is_timed_in_full():
    m = FakeMachine({1: 0.10, 2: 0.125})  # 1.25x: under the abort factor, so every probe step is timed
    gov = governor(m, probe_steps=4, period=100.0)
    used = m.train(gov, 30)
    assert used[:10] == [1] * 5 + [2] * 5 and set(used[10:]) == {1}


def test_an_idle_machine_keeps_two_threads():
    m = FakeMachine({1: 0.10, 2: 0.07})
    gov = governor(m, probe_steps=4, period=100.0)
    used = m.train(gov, 60)
    assert set(used[10:]) == {2} and gov.decisions[0]["chose"] == 2


def test_the_choice_follows_the_load_at_the_next_probe():
    m = FakeMachine({1: 0.10, 2: 0.07})
    gov = governor(m, probe_steps=3, period=5.0)
    m.train(gov, 20)
    assert gov.current == 2
    m.step_seconds[2] = 0.40  # another job took the second core
    m.train(gov, 200)
    assert gov.current == 1 and gov.decisions[-1]["chose"] == 1
    assert len(gov.decisions) >= 2


def test_one_thread_asked_changes_nothing():
    m = FakeMachine({1: 0.1})
    gov = governor(m, max_threads=1)
    m.train(gov, 30)
    assert m.sets == [1] and gov.decisions == []


def test_a_tie_goes_to_fewer_threads_and_bad_arguments_are_refused():
    m = FakeMachine({1: 0.125, 2: 0.125})  # exact in binary: equal medians
    gov = governor(m, probe_steps=2)
    m.train(gov, 10)
    assert gov.current == 1
    with pytest.raises(ValueError, match="max_threads"):
        ThreadGovernor(0, set_threads=m.set_threads)
    with pytest.raises(ValueError, match="period"):
        ThreadGovernor(2, period=0, set_threads=m.set_threads)
