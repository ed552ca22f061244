"""The thread governor picks the count whose measured steps are fastest, and re-probes on a change."""

import pytest

from prismonet.threads import ThreadGovernor


def drive(gov, cost, steps):
    """Run ``steps`` steps whose time is ``cost(threads, step)``; return the counts used."""
    used = []
    for i in range(steps):
        n = gov.before_step()
        used.append(n)
        gov.after_step(cost(n, i))
    return used


def test_quiet_machine_keeps_two_threads():
    applied = []
    gov = ThreadGovernor((1, 2), period=10, probe=3, set_threads=applied.append)
    used = drive(gov, lambda n, i: {1: 0.19, 2: 0.135}[n], 30)
    assert used[:6] == [1, 1, 1, 2, 2, 2]  # the probe: each candidate in turn
    assert used[6:16] == [2] * 10  # then the faster for a period
    assert gov.history[0] == (6, {1: 0.19, 2: 0.135})
    assert applied[0] == 1 and applied[1] == 2  # set only on a change


def test_loaded_machine_switches_to_one_thread():
    """Under load the first 2-thread step of a probe is 2.6x the 1-thread median, so the probe stops there."""
    gov = ThreadGovernor((1, 2), period=50, probe=3, set_threads=lambda n: None)
    used = drive(gov, lambda n, i: {1: 0.217, 2: 0.555}[n], 20)
    assert used[:4] == [1, 1, 1, 2] and used[4:] == [1] * 16
    assert gov.history[0] == (4, {1: 0.217, 2: 0.555})
    every = ThreadGovernor((1, 2), period=50, probe=3, cut_factor=None, set_threads=lambda n: None)
    assert drive(every, lambda n, i: {1: 0.217, 2: 0.555}[n], 20)[:7] == [1, 1, 1, 2, 2, 2, 1]


def test_a_probe_cuts_a_candidate_only_on_its_first_step_and_only_when_far_slower():
    """1.4x slower is not cut at the 1.5 default; a first step 1.6x slower is; a slow second step never cuts."""
    gov = ThreadGovernor((1, 2), period=50, probe=3, set_threads=lambda n: None)
    assert drive(gov, lambda n, i: {1: 0.2, 2: 0.28}[n], 8)[:7] == [1, 1, 1, 2, 2, 2, 1]
    gov = ThreadGovernor((1, 2), period=50, probe=3, set_threads=lambda n: None)
    assert drive(gov, lambda n, i: {1: 0.2, 2: 0.32}[n], 6)[:5] == [1, 1, 1, 2, 1]
    gov = ThreadGovernor((1, 2), period=50, probe=3, set_threads=lambda n: None)
    late = lambda n, i: 0.9 if (n == 2 and i == 4) else {1: 0.2, 2: 0.15}[n]
    assert drive(gov, late, 8)[:7] == [1, 1, 1, 2, 2, 2, 2] and gov.choice == 2


def test_load_change_triggers_an_early_probe():
    gov = ThreadGovernor((1, 2), period=1000, probe=2, slow_factor=2.0, set_threads=lambda n: None)
    # quiet for 10 steps, then another process arrives: 2 threads become 4x slower
    cost = lambda n, i: {1: 0.19, 2: 0.135}[n] if i < 10 else {1: 0.22, 2: 0.55}[n]
    used = drive(gov, cost, 22)
    assert used[4:10] == [2] * 6
    assert used[10:12] == [2, 2]  # the two slow steps in a row that reveal the load...
    assert used[12:15] == [1, 1, 2]  # ...start a probe at once, whose 2-thread step, 2.5x slower, ends it
    assert used[15:] == [1] * 7
    assert len(gov.history) == 2


def test_one_slow_step_is_not_a_load_change():
    """A lone hiccup (one step over the slow factor) does not start a probe; ``slow_steps=1`` restores the
    old rule, where it did."""
    hiccup = lambda n, i: 0.5 if i == 8 else {1: 0.19, 2: 0.135}[n]
    gov = ThreadGovernor((1, 2), period=1000, probe=2, set_threads=lambda n: None)
    assert drive(gov, hiccup, 16)[4:] == [2] * 12 and len(gov.history) == 1
    eager = ThreadGovernor((1, 2), period=1000, probe=2, slow_steps=1, set_threads=lambda n: None)
    assert drive(eager, hiccup, 16)[9:13] == [1, 1, 2, 2] and len(eager.history) == 2


def test_probes_that_keep_the_choice_back_off_and_a_change_resets_the_wait():
    """Under a lasting load every probe pays 2-thread steps: the wait doubles (10, 20, 40, capped at 40) while
    the probes keep 1 thread, and returns to 10 once a probe picks another count."""
    gov = ThreadGovernor((1, 2), period=10, probe=1, max_period=40, set_threads=lambda n: None)
    loaded = lambda n, i: {1: 0.217, 2: 0.555}[n]
    drive(gov, loaded, 2 + 10 + 2 + 20 + 2 + 40 + 2 + 40 + 2)
    starts = [step for step, _ in gov.history]
    assert [b - a for a, b in zip(starts, starts[1:])] == [12, 22, 42, 42]
    # the load leaves: the next probe picks 2 threads, and the wait is `period` again
    drive(gov, lambda n, i: {1: 0.19, 2: 0.135}[n], 40 + 2 + 10 + 2)
    starts = [step for step, _ in gov.history]
    assert gov.choice == 2 and starts[-1] - starts[-2] == 12


@pytest.mark.parametrize("kw", [dict(candidates=()), dict(candidates=(0, 1)), dict(candidates=(1,), period=0),
                                dict(candidates=(1,), slow_factor=1.0), dict(candidates=(1,), period=10, max_period=5),
                                dict(candidates=(1,), slow_steps=0), dict(candidates=(1,), cut_factor=1.0)])
def test_rejects_bad_settings(kw):
    with pytest.raises(ValueError):
        ThreadGovernor(set_threads=lambda n: None, **kw)
