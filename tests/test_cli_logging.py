"""``skinlayers -v`` / ``-vv``: the toolkit's log records on stderr; silent without."""

from __future__ import annotations

import logging

import pytest
from typer.testing import CliRunner

from skinlayers.cli import app, show_logs


@pytest.fixture()
def toolkit_logger():
    root = logging.getLogger("skinlayers")
    handlers, level = list(root.handlers), root.level
    yield root
    root.handlers[:] = handlers
    root.setLevel(level)


@pytest.mark.parametrize("flags, level", [([], logging.WARNING), (["-v"], logging.INFO), (["-vv"], logging.DEBUG),
                                          (["--verbose", "--verbose", "-v"], logging.DEBUG)])
def test_the_flag_sets_the_toolkit_level(toolkit_logger, flags, level):
    result = CliRunner().invoke(app, [*flags, "skin-types"])
    assert result.exit_code == 0, result.output
    assert toolkit_logger.level == level


def test_records_reach_stderr_once_and_only_when_asked(toolkit_logger, capsys):
    fit_log = logging.getLogger("skinlayers.reconstruct.mapfit.fit")
    show_logs(0)
    fit_log.info("level 1 of 3")
    assert "level 1 of 3" not in capsys.readouterr().err
    show_logs(1)
    show_logs(1)  # a second call adds no second handler
    fit_log.info("level 2 of 3")
    fit_log.debug("not at -v")
    err = capsys.readouterr().err
    assert err.count("level 2 of 3") == 1 and "not at -v" not in err
