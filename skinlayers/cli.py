"""The one ``skinlayers`` command; each part of the toolkit contributes its subcommands.

Errors a user can cause (bad values, files, settings) end with one line on stderr and exit status 1;
usage errors (unknown options) exit 2 as usual; nothing prints a traceback unless ``SKINLAYERS_DEBUG``
is set.
"""

from __future__ import annotations

import os
import sys

import typer

from . import demo as demo_cli
from .acquire import cli as acquire_cli
from .acquire.devices import DeviceError
from .calibration import cli as calibration_cli
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
model_cli.register(app)
acquire_cli.register(app)
calibration_cli.register(app)
reconstruct_cli.register(app)
demo_cli.register(app)


def main() -> None:
    try:
        app()
    except (ValueError, OSError, KeyError, DeviceError) as exc:
        if os.environ.get("SKINLAYERS_DEBUG"):
            raise
        message = " ".join(str(exc).split()) or exc.__class__.__name__
        typer.echo(f"error: {message}", err=True)
        sys.exit(1)


if __name__ == "__main__":
    main()
