"""Shared test set-up: every test builds its Gaussian tables in one temporary cache, never in ~/.cache."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session", autouse=True)
def _table_cache(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("SKINLAYERS_CACHE", str(tmp_path_factory.mktemp("skinlayers-cache")))
    yield
    mp.undo()
