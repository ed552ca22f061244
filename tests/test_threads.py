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


# --- the command line's start-up thread count (prismonet.threads.threads_for_load, prismonet.threads.use_free_cores) ---

STAT = """cpu  {u} 0 {s} {i} {w} 0 0 0 0 0
cpu0 1 0 1 1 0 0 0 0 0 0
cpu1 1 0 1 1 0 0 0 0 0 0
intr 12345
"""


def test_cpu_ticks_and_busy_cores_by_hand():
    from prismonet.threads import busy_between, cpu_ticks

    a = cpu_ticks(STAT.format(u=1000, s=200, i=5000, w=100))
    assert a == (2, 6300, 5100)
    # 200 ticks pass on the 2 cpus: 120 user + 30 system busy, 40 idle + 10 iowait -> 150 / 200 of 2 cores
    b = cpu_ticks(STAT.format(u=1120, s=230, i=5040, w=110))
    assert busy_between(a, b) == pytest.approx(1.5)
    assert busy_between(a, a) is None  # no time passed
    assert busy_between(a, (4, 7000, 5200)) is None  # another cpu count
    assert cpu_ticks("") is None and cpu_ticks("intr 1 2 3 4 5 6\n") is None and cpu_ticks("cpu a b c d e f g h\n") is None


@pytest.mark.parametrize("busy, want", [(None, 2), (0.0, 2), (0.4, 2), (0.6, 1), (1.0, 1), (2.0, 1), (3.5, 1)])
def test_threads_for_load_on_two_cores(busy, want):
    from prismonet.threads import threads_for_load

    assert threads_for_load(2, busy, 2) == want


def test_threads_for_load_takes_the_free_cores_up_to_the_default():
    from prismonet.threads import threads_for_load

    assert threads_for_load(16, 5.2, 16) == 11
    assert threads_for_load(16, 0.0, 8) == 8  # never more than torch's own choice
    assert threads_for_load(16, 15.9, 16) == 1


def test_prismonet_threads_sets_the_count_and_a_bad_value_is_one_line(monkeypatch):
    import torch

    from prismonet.threads import use_free_cores

    before = torch.get_num_threads()
    try:
        monkeypatch.setenv("PRISMONET_THREADS", "1")
        use_free_cores()
        assert torch.get_num_threads() == 1
        monkeypatch.setenv("PRISMONET_THREADS", "two")
        with pytest.raises(ValueError, match="PRISMONET_THREADS must be a positive whole number"):
            use_free_cores()
    finally:
        torch.set_num_threads(before)


def test_command_line_run_on_a_loaded_machine_takes_one_thread(monkeypatch, capsys):
    """``main()`` as the command line calls it (no argv) measures the load; a test's ``main([...])`` does not."""
    import sys

    import torch

    import prismonet.threads as threads
    from prismonet.cli import main

    import os

    before = torch.get_num_threads()
    calls = []
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    monkeypatch.setattr(threads, "busy_cores", lambda *a, **k: calls.append(1) or float(cores))  # every core busy
    monkeypatch.setattr(threads, "follow_ceiling", None)  # restored after the test: main() sets it
    monkeypatch.delenv("PRISMONET_THREADS", raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    try:
        torch.set_num_threads(2)
        assert main(["data", "verify", "/nonexistent/data"]) == 2 and not calls  # argv given: untouched
        assert threads.follow_ceiling is None
        monkeypatch.setattr(sys, "argv", ["prismonet", "data", "verify", "/nonexistent/data"])
        main()
        assert calls and torch.get_num_threads() == 1
        assert threads.follow_ceiling == 2  # a long command may go back up to torch's own count
        assert f"other processes keep {cores:.1f} cores busy: running on 1 thread" in capsys.readouterr().err
    finally:
        torch.set_num_threads(before)


@pytest.mark.skipif(not hasattr(__import__("os"), "sched_getaffinity") or len(__import__("os").sched_getaffinity(0)) < 2,
                    reason="needs 2 cores this process may run on")
def test_follow_load_takes_the_cores_the_load_frees(monkeypatch):
    """``follow_load``: on 2 cores, a busy core gives 1 thread, a quiet machine the ceiling again; ``None`` where the
    count did not change, and nothing at all without a ceiling (a library call, or a count set by the user)."""
    import torch

    import prismonet.threads as threads

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        monkeypatch.setattr(threads, "follow_ceiling", None)
        assert threads.follow_load(lambda: 2.0) is None and torch.get_num_threads() == 2
        monkeypatch.setattr(threads, "follow_ceiling", 2)
        assert threads.follow_load(lambda: 1.0) == 1 and torch.get_num_threads() == 1
        assert threads.follow_load(lambda: 1.0) is None  # unchanged
        assert threads.follow_load(lambda: None) is None and torch.get_num_threads() == 1  # unmeasurable: left as is
        assert threads.follow_load(lambda: 0.2) == 2 and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_distillation_follows_the_load_before_each_chunk(monkeypatch, tmp_path):
    """``fit_targets`` asks ``follow_load`` before each chunk it computes, and not for a chunk that exists."""
    import prismonet.threads as threads
    from prismonet.assets import shipped_samples
    from prismonet.data.dataset import SceneDataset
    from prismonet.model.distill_fit import fit_targets
    from prismonet.model.inference import InferenceConfig
    from prismonet.model.io import load_model

    calls = []
    monkeypatch.setattr(threads, "follow_load", lambda *a, **k: calls.append(1))
    model = load_model("shipped")[0]
    ds = SceneDataset(shipped_samples(), split="test")
    fit_targets(model, ds, tmp_path / "t", 2, InferenceConfig(), batch_size=2, progress=False)
    assert calls == [1]
    fit_targets(model, ds, tmp_path / "t", 2, InferenceConfig(), batch_size=2, progress=False)  # resumed: nothing left
    assert calls == [1]


def test_a_script_takes_the_same_thread_choice_and_says_a_bad_value_in_one_line(monkeypatch, capsys):
    """``use_free_cores(exit_on_error=True)``, as the scripts in ``scripts/`` call it: the count is set the same way, and
    a bad ``PRISMONET_THREADS`` is one line on stderr and exit status 2 instead of a traceback."""
    import torch

    from prismonet.threads import use_free_cores

    before = torch.get_num_threads()
    try:
        monkeypatch.setenv("PRISMONET_THREADS", "1")
        use_free_cores(exit_on_error=True)
        assert torch.get_num_threads() == 1
        monkeypatch.setenv("PRISMONET_THREADS", "0")
        with pytest.raises(SystemExit) as e:
            use_free_cores(exit_on_error=True)
        assert e.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].endswith("error: PRISMONET_THREADS must be a positive whole number, got '0'")
    finally:
        torch.set_num_threads(before)
