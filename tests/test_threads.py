"""The thread policy (``formats/threads.py``): the usable cores less the busy ones, at least one;
``--threads`` and ``SKINLAYERS_THREADS`` override it; bad values are refused in one line."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

from skinlayers.formats import threads as policy
from skinlayers.formats.errors import InputError
from skinlayers.formats.threads import THREADS_ENV, choose_threads, idle_cpus, library_threads, usable_cpus


@pytest.fixture()
def torch_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_auto_takes_the_idle_usable_cores_and_at_least_one(monkeypatch):
    monkeypatch.delenv(THREADS_ENV, raising=False)
    monkeypatch.setattr(policy, "usable_cpus", lambda: 4)
    for idle, expected in ((4.0, 4), (3.0, 3), (1.0, 1), (0.0, 1), (8.0, 4)):
        monkeypatch.setattr(policy, "idle_cpus", lambda sample_s=0.0, idle=idle: idle)
        choice = choose_threads()
        assert choice.threads == expected and "idle" in choice.reason, (idle, choice)
    monkeypatch.setattr(policy, "idle_cpus", lambda sample_s=0.0: None)  # no /proc/stat: every usable core
    assert choose_threads().threads == 4


def test_asked_for_overrides_the_environment_which_overrides_auto(monkeypatch):
    monkeypatch.setattr(policy, "idle_cpus", lambda sample_s=0.0: 0.0)
    monkeypatch.setenv(THREADS_ENV, "3")
    assert choose_threads().threads == 3 and THREADS_ENV in choose_threads().reason
    assert choose_threads("2").threads == 2 and "--threads" in choose_threads("2").reason
    monkeypatch.setenv(THREADS_ENV, "auto")
    assert choose_threads().threads == 1


@pytest.mark.parametrize("bad", ["0", "-2", "two", "1.5"])
def test_bad_counts_are_refused_naming_where_they_came_from(monkeypatch, bad):
    with pytest.raises(InputError, match="--threads"):
        choose_threads(bad)
    monkeypatch.setenv(THREADS_ENV, bad)
    with pytest.raises(InputError, match=THREADS_ENV):
        choose_threads()


def test_usable_cores_are_within_the_affinity():
    assert 1 <= usable_cpus() <= len(os.sched_getaffinity(0))


def test_a_core_kept_busy_is_not_counted_idle():
    """A busy loop pinned to one of this process's cores: that core is not among the idle ones."""
    mine = sorted(os.sched_getaffinity(0))
    code = "import os, time\nos.sched_setaffinity(0, {%d})\nt = time.time()\nwhile time.time() - t < 3: pass\n" % mine[0]
    busy = subprocess.Popen([sys.executable, "-c", code])
    try:
        idle = idle_cpus(0.5)
    finally:
        busy.kill()
        busy.wait()
    assert idle is not None and idle <= len(mine) - 1


def test_the_library_follows_the_environment_only_where_it_is_set(monkeypatch, torch_threads):
    from skinlayers.formats import threads

    monkeypatch.setattr(threads, "_applied", None)
    torch.set_num_threads(1)
    monkeypatch.delenv(THREADS_ENV, raising=False)
    assert library_threads() is None and torch.get_num_threads() == 1
    monkeypatch.setenv(THREADS_ENV, "2")
    assert library_threads().threads == 2 and torch.get_num_threads() == 2


def test_a_commands_threads_win_over_the_environment_in_the_library(monkeypatch, torch_threads):
    from skinlayers.formats import threads

    monkeypatch.setattr(threads, "_applied", None)  # restored after the test
    monkeypatch.setenv(THREADS_ENV, "2")
    threads.use_threads(choose_threads(1))  # what `--threads 1` does before the command calls the library
    assert library_threads().threads == 1 and torch.get_num_threads() == 1


def test_commands_refuse_bad_counts_in_one_line(run_cli, tmp_path, torch_threads):
    code, _, err = run_cli("calibrate", str(tmp_path / "no-session"), "--threads", "1")
    assert code == 1 and err.strip().startswith("error:") and "\n" not in err.strip(), err  # the error alone, one line
    code, _, err = run_cli("calibrate", str(tmp_path / "no-session"), "--threads", "none")
    assert code == 1 and "--threads: threads must be a whole number" in err, err
