"""Shared test set-up: every test builds its Gaussian tables in one temporary cache, never in ~/.cache;
``run_cli`` runs the ``skinlayers`` command in the test's process; the transport reference
(``tests/model/transport_reference.py``), which the model's tests and the transport chart both use,
is importable as ``transport_reference`` (the test folders are not packages)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

_MODEL_TESTS = str(Path(__file__).resolve().parent / "model")
if _MODEL_TESTS not in sys.path:
    sys.path.insert(0, _MODEL_TESTS)


@pytest.fixture(scope="session", autouse=True)
def _table_cache(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("SKINLAYERS_CACHE", str(tmp_path_factory.mktemp("skinlayers-cache")))
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
