"""Shared test set-up: every test builds its Gaussian tables in one temporary cache, never in ~/.cache;
``run_cli`` runs the ``skinlayers`` command in the test's process; the transport reference
(``tests/model/transport_reference.py``), which the model's tests and the transport chart both use,
is importable as ``transport_reference`` (the test folders are not packages)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

#: Under pytest-xdist each worker takes one core: one torch thread apiece (set before torch starts its
#: pool, and inherited by the commands the tests run), else the workers' threads oversubscribe the cores.
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    # the thread policy (formats/threads.py) of the commands and library calls the tests make: one
    os.environ.setdefault("SKINLAYERS_THREADS", "1")

#: The default selection (pyproject's addopts); any other ``-m`` (benchmarks, slow checks) runs in one
#: process: benchmarks time themselves with two threads and print their tables.
DEFAULT_MARKS = "not slow and not bench"
#: Workers for the default run: two cores' worth (more would rebuild every shared fixture once more).
DEFAULT_WORKERS = 2


def pytest_xdist_auto_num_workers(config):
    """``-n auto``: ``DEFAULT_WORKERS`` for the default selection on a machine with that many cores, else none."""
    if (config.getoption("markexpr") or "") != DEFAULT_MARKS or (os.cpu_count() or 1) < DEFAULT_WORKERS:
        return 0
    return DEFAULT_WORKERS


_MODEL_TESTS = str(Path(__file__).resolve().parent / "model")
if _MODEL_TESTS not in sys.path:
    sys.path.insert(0, _MODEL_TESTS)


@pytest.fixture(scope="session", autouse=True)
def _table_cache(tmp_path_factory, worker_id):
    """One table cache for the run, shared by xdist's workers (tables are written atomically: a worker
    never reads another's half-written file; at worst both build the same table once)."""
    mp = pytest.MonkeyPatch()
    base = tmp_path_factory.getbasetemp()
    folder = (base.parent if worker_id != "master" else base) / "skinlayers-cache"
    folder.mkdir(exist_ok=True)
    mp.setenv("SKINLAYERS_CACHE", str(folder))
    if worker_id != "master":
        import torch

        torch.set_num_threads(1)
    yield
    mp.undo()


@pytest.fixture
def run_cli(monkeypatch, capsys):
    """``run_cli(*args)`` → (exit status, stdout, stderr) of ``skinlayers ARGS`` (status 0 when it returns)."""
    from skinlayers.cli import main

    def run(*args: str) -> tuple[int, str, str]:
        monkeypatch.setattr(sys, "argv", ["skinlayers", *args])
        code = 0
        try:
            main()
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
        out = capsys.readouterr()
        return code, out.out, out.err

    return run


#: The files that take longest in the default run (each on one worker: ``--dist loadfile``), handed out
#: first so that no worker is left alone with one of them at the end (the order: docs/speed.md, "The
#: suite"); the rest keep their collected order after them.
HEAVY_FIRST = ("test_stability.py", "test_batch.py", "test_tradeoff.py", "test_demo.py", "reconstruct/test_absorbers.py",
               "reconstruct/test_fit_forward.py", "model/test_coupling.py", "reconstruct/test_uncertainty.py",
               "reconstruct/test_fit_recovery.py", "reconstruct/test_fit_grids.py", "reconstruct/test_fit_robustness.py",
               "calibration/test_calibration_simulated.py", "test_band_design.py", "test_cli.py")


def _heaviness(item) -> int:
    path = Path(str(item.fspath)).as_posix()
    return next((k for k, name in enumerate(HEAVY_FIRST) if path.endswith("/tests/" + name)), len(HEAVY_FIRST))


def pytest_collection_modifyitems(config, items):
    """The heavy files first (``HEAVY_FIRST``), each file's tests in their own order (a stable sort)."""
    items.sort(key=_heaviness)
