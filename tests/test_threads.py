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
    gov = ThreadGovernor((1, 2), period=50, probe=3, set_threads=lambda n: None)
    used = drive(gov, lambda n, i: {1: 0.217, 2: 0.555}[n], 20)
    assert used[6:] == [1] * 14


def test_load_change_triggers_an_early_probe():
    gov = ThreadGovernor((1, 2), period=1000, probe=2, slow_factor=2.0, set_threads=lambda n: None)
    # quiet for 10 steps, then another process arrives: 2 threads become 4x slower
    cost = lambda n, i: {1: 0.19, 2: 0.135}[n] if i < 10 else {1: 0.22, 2: 0.55}[n]
    used = drive(gov, cost, 20)
    assert used[4:10] == [2] * 6
    assert used[10] == 2  # the slow step that reveals the load...
    assert used[11:15] == [1, 1, 2, 2]  # ...starts a probe at once
    assert used[15:] == [1] * 5
    assert len(gov.history) == 2


@pytest.mark.parametrize("kw", [dict(candidates=()), dict(candidates=(0, 1)), dict(candidates=(1,), period=0),
                                dict(candidates=(1,), slow_factor=1.0)])
def test_rejects_bad_settings(kw):
    with pytest.raises(ValueError):
        ThreadGovernor(set_threads=lambda n: None, **kw)
