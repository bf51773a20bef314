"""The one ``skinlayers`` command; each part of the toolkit contributes its subcommands.

Errors a user can cause (``formats.errors.SkinlayersError``: bad values, files, settings, an instrument
that does not answer; and ``OSError``: a missing file, a full disk) end with one line on stderr and exit
status 1; usage errors (unknown options) exit 2 as usual. Anything else is a bug and keeps its traceback;
``SKINLAYERS_DEBUG`` shows the traceback of a user error too.
"""

from __future__ import annotations

import logging
import os
import sys

import typer

from . import demo as demo_cli
from .analyses import band_design
from .analyses import stability as stability_analysis
from .analyses import tradeoff as tradeoff_analysis
from .studies import batch_cli
from .acquire import cli as acquire_cli
from .calibration import cli as calibration_cli
from .formats.errors import SkinlayersError
from .model import cli as model_cli
from .reconstruct import cli as reconstruct_cli

app = typer.Typer(
    name="skinlayers",
    help=(
        "Multi-spectral skin acquisition and inverse rendering with a layered, heterogeneous, "
        "spectral skin model (Donner et al. 2008)."
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
#: ``-v``: what the acquisition, calibration and fit do, step by step; ``-vv``: also every command sent
#: to the filter wheel and the camera, with their answers.
_LOG_LEVELS = {0: logging.WARNING, 1: logging.INFO, 2: logging.DEBUG}


@app.callback()
def _options(
    verbose: int = typer.Option(
        0, "--verbose", "-v", count=True,
        help="Log on stderr what the instruments and the pipeline do: -v each step, -vv also every device command.",
    ),
) -> None:
    """Multi-spectral skin acquisition and inverse rendering (Donner et al. 2008)."""
    show_logs(verbose)


def show_logs(verbosity: int) -> None:
    """Send the toolkit's log records of the verbosity's level to stderr (rich's handler, times shown)."""
    from rich.console import Console  # noqa: PLC0415 (only when asked for)
    from rich.logging import RichHandler  # noqa: PLC0415

    root = logging.getLogger("skinlayers")
    root.setLevel(_LOG_LEVELS[min(verbosity, 2)])
    if verbosity and not any(isinstance(h, RichHandler) for h in root.handlers):
        root.addHandler(RichHandler(console=Console(stderr=True), show_path=False, markup=False))


model_cli.register(app)
acquire_cli.register(app)
calibration_cli.register(app)
reconstruct_cli.register(app)
demo_cli.register(app)
tradeoff_analysis.register(app)
stability_analysis.register(app)
batch_cli.register(app)
band_design.register(app)


def command():
    """The ``skinlayers`` command as click runs it, its on/off and counted options (``--help`` too) shown
    without a type placeholder in ``--help``: ``--force`` is a switch, and a ``<bool>`` beside it reads as
    if it took a value."""
    group = typer.main.get_command(app)
    for sub in _commands(group):
        help_option = sub.get_help_option(sub.context_class(sub))  # made once and kept by the command
        for param in [*sub.params, *([help_option] if help_option is not None else [])]:
            if getattr(param, "is_flag", False) or getattr(param, "count", False):
                param.metavar = ""
    return group


def _commands(cmd) -> list:
    """``cmd`` and every command under it."""
    return [cmd, *(c for sub in getattr(cmd, "commands", {}).values() for c in _commands(sub))]


def main() -> None:
    try:
        command()(prog_name="skinlayers")
    except (SkinlayersError, OSError) as exc:
        if os.environ.get("SKINLAYERS_DEBUG"):
            raise
        message = " ".join(str(exc).split()) or exc.__class__.__name__
        typer.echo(f"error: {message}", err=True)
        sys.exit(1)


if __name__ == "__main__":
    main()
