"""``skinlayers batch``, the command: its options checked before any worker starts, a bar over the
sessions, the study's table and figures written (the work is ``skinlayers.studies.batch``)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional, Sequence

import typer

from ..formats.errors import InputError
from .batch import (DEVICES, LEDGER_NAME, MANIFEST_COLUMNS, STEPS, BatchOptions, SessionOutcome, StudySession, default_study_out,
                    read_study, run_batch, write_study)

__all__ = ["batch", "register"]


def batch(
    study: Path = typer.Argument(..., help="A folder of sessions (each folder below it holding manifest.json) or a CSV "
                                           "listing them (a 'session' column, paths relative to the CSV; other columns kept)."),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="Where the study's table, record and figures go "
                                                                 "(default: <STUDY>_study beside it)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="A Dask scheduler's address (tcp://host:8786); default: "
                                                                      "a LocalCluster on this machine."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Worker processes of the LocalCluster (default: one per "
                                                                  "GPU, else one per usable core)."),
    steps: str = typer.Option(",".join(STEPS), "--steps", help="Steps of each session: calibrate, reconstruct or both."),
    config: Optional[Path] = typer.Option(None, "--config", help="Fit settings YAML (configs/fit.yaml lists every key)."),
    calibration_config: Optional[Path] = typer.Option(None, "--calibration-config", help="Calibration settings YAML."),
    group: list[str] = typer.Option([], "--group", help="A column to group the statistics by (repeatable; default: every "
                                                        "column that groups sessions)."),
    device: str = typer.Option("auto", "--device", help="cpu, cuda or auto (each worker its GPU where there are GPUs)."),
) -> None:
    """Calibrate and reconstruct every session of a study on Dask, then its statistics.

    Example: skinlayers batch my-study               (a LocalCluster here; outputs beside each session)
             skinlayers batch study.csv --scheduler tcp://10.0.0.5:8786   (a Dask cluster: docs/batch.md)
    A rerun does only what is missing (failed sessions again); batch.json records every session's outcome.
    """
    sessions = read_study(study)
    options = _checked_options(steps, config, calibration_config, device, workers, scheduler)
    _check_groups(group, sessions)
    out = out or default_study_out(study)
    from ..formats.outputs import refuse_inside_session  # noqa: PLC0415

    refuse_inside_session(out, "study")
    typer.echo(f"study: {len(sessions)} session(s) from {study}; steps {', '.join(options.steps)}", err=True)
    with _study_progress(len(sessions)) as on_outcome:
        result = run_batch(sessions, options, out, scheduler=scheduler, workers=workers, on_outcome=on_outcome)
    paths = write_study(out, sessions, result.outcomes, group)
    typer.echo(f"{result.count('done')} done, {result.count('skipped')} already complete, {result.count('failed')} failed "
               f"on {result.workers} worker(s) in {result.wall_s:.0f} s")
    for o in result.outcomes.values():
        if o.status == "failed":
            typer.echo(f"failed: {o.session}: {o.error}")
    for kind, path in {"ledger": out / LEDGER_NAME, **paths}.items():
        typer.echo(f"{kind}: {path}")
    if result.count("failed"):
        raise typer.Exit(1)


def _checked_options(steps: str, config: Path | None, calibration_config: Path | None, device: str,
                     workers: int | None, scheduler: str | None) -> BatchOptions:
    """The options checked, and the settings files read, before any worker starts."""
    from ..calibration.settings import load_calibration_settings  # noqa: PLC0415
    from ..reconstruct import load_fit_settings  # noqa: PLC0415

    chosen = tuple(s.strip() for s in steps.split(",") if s.strip())
    if not chosen or any(s not in STEPS for s in chosen):
        raise InputError(f"--steps {steps!r}: choose from {', '.join(STEPS)}, comma-separated")
    if device not in DEVICES:
        raise InputError(f"--device {device!r}: expected {', '.join(DEVICES)}")
    if workers is not None and workers < 1:
        raise InputError(f"--workers {workers}: expected at least 1")
    if workers is not None and scheduler is not None:
        raise InputError("--workers sizes the LocalCluster; with --scheduler the cluster's own workers run the tasks "
                         "(start more with `dask worker`)")
    return BatchOptions(tuple(s for s in STEPS if s in chosen), load_fit_settings(config),
                        load_calibration_settings(calibration_config), device)


def _check_groups(group: Sequence[str], sessions: Sequence[StudySession]) -> None:
    """``--group`` columns must be the study list's or the manifest's, refused before any work."""
    known = {*MANIFEST_COLUMNS, *(c for s in sessions for c in s.columns)}
    unknown = [g for g in group if g not in known]
    if unknown:
        raise InputError(f"--group {', '.join(unknown)}: not a column of the study (its columns: {', '.join(sorted(known))})")


class _study_progress:
    """A bar over the study's sessions with the time left; each outcome advances it."""

    def __init__(self, total: int) -> None:
        from rich.console import Console  # noqa: PLC0415
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn  # noqa: PLC0415

        self.progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                                 TextColumn("left"), TimeRemainingColumn(), console=Console(stderr=True))
        self.task = self.progress.add_task("sessions", total=total)
        self.failed = 0

    def __enter__(self) -> Callable[[SessionOutcome], None]:
        self.progress.start()
        return self.advance

    def advance(self, outcome: SessionOutcome) -> None:
        self.failed += outcome.status == "failed"
        self.progress.update(self.task, advance=1, description=f"sessions ({self.failed} failed)" if self.failed else "sessions")
        if outcome.status == "failed":
            self.progress.console.print(f"failed: {outcome.session}: {outcome.error}")

    def __exit__(self, *exc) -> None:
        self.progress.stop()


def register(app: typer.Typer) -> None:
    app.command("batch")(batch)
