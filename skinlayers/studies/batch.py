"""``skinlayers batch``: a study's sessions calibrated and reconstructed as Dask tasks, then its statistics.

A study is a folder of sessions (every folder below it holding ``manifest.json``) or a CSV listing them
(a ``session`` column, paths relative to the CSV, and any other columns: subject, site, skin type,
date, …). Each session is one task (``process_session``): its calibration into ``<SESSION>_calibrated``
and its fit into ``<SESSION>_reconstruction`` beside it, as ``skinlayers calibrate`` and ``reconstruct``
write them, then the session's row of the study table (``study.session_summary``).

The tasks run on Dask distributed: a ``LocalCluster`` on this machine by default (one worker process
per usable core, each task on one torch thread; one worker per GPU where there are GPUs), or the
cluster behind ``--scheduler ADDRESS`` (``dask scheduler`` and ``dask worker`` on the cluster's
machines, or ``dask-jobqueue`` under SLURM or PBS: docs/batch.md).

What a study can rely on:

- **Resumable.** A step whose outputs are complete (``calibration.json``, ``fit.json``: written last,
  ``formats/outputs.py``) is not run again; a rerun of the same study does only what is missing.
- **A failed session does not stop the others.** Its error is recorded (``batch.json``, ``study.csv``)
  and the next run tries it again.
- **A worker lost mid-task** (killed, out of memory, its machine gone) has its task rerun on another
  by the Dask scheduler; the outputs of the lost attempt were never moved into place, and the folder's
  lock of the dead process is taken over by a rerun on the same machine (one left on another machine is
  refused; docs/batch.md).
- ``batch.json`` is rewritten (atomically) after every session, so an interrupted batch shows what it
  did; the study's table, record and figures are written when the tasks are done.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import os
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Sequence


from ..formats.cube import CALIBRATED_SUFFIX, RECONSTRUCTION_SUFFIX, reconstruction_dir
from ..formats.errors import InputError
from ..formats.files import atomic_write
from .allocator import use_task_allocator
from .study import is_map_column, session_summary, study_record, without_nan, write_study_json, write_study_table

__all__ = ["BatchOptions", "BatchResult", "SessionOutcome", "StudySession", "default_study_out", "process_session",
           "read_study", "run_batch", "study_rows", "write_study"]

log = logging.getLogger(__name__)

STEPS = ("calibrate", "reconstruct")
#: Columns each session gives from its manifest where the study's list does not: column → manifest key.
MANIFEST_COLUMNS = {"subject": "subject", "site": "site", "date": "created"}
LEDGER_NAME, TABLE_NAME, RECORD_NAME = "batch.json", "study.csv", "study.json"
#: Columns the study table writes itself: a study's list may not name its own columns so.
RESERVED_COLUMNS = ("status", "error", "seconds", "pixels")
#: A hyperspectral camera's dark and white reference captures beside its cubes (Specim's names): not skin.
REFERENCE_CAPTURES = ("DARKREF", "WHITEREF")
#: The study's own folder: ``<STUDY>_study`` beside the study.
STUDY_SUFFIX = "_study"
DEVICES = ("cpu", "cuda", "auto")
#: Dask's nanny starts each worker with ``MALLOC_TRIM_THRESHOLD_=65536``, which fixes glibc's mmap threshold:
#: every tensor temporary is then mapped and unmapped anew, and the fit slows down (docs/batch.md,
#: "Workers started outside skinlayers"). Unset for our workers; a task on any other worker sets the allocator
#: itself (``allocator.use_task_allocator``).
WORKER_ENVIRON = {"MALLOC_TRIM_THRESHOLD_": None}
#: Torch threads of each task: one per worker process, one worker per core (formats/threads.py says why).
TASK_THREADS = 1


@dataclass(frozen=True)
class StudySession:
    """A session of the study: its folder, its name in the study, and the columns its list gives it."""

    path: Path
    name: str
    columns: dict = field(default_factory=dict)


@dataclass(frozen=True)
class BatchOptions:
    """What each task does: its steps, the settings (loaded and checked before any task), where it runs."""

    steps: tuple[str, ...] = STEPS
    fit_settings: object = None  # reconstruct.settings.FitSettings; None: the defaults
    calibration_settings: object = None  # calibration.settings.CalibrationSettings; None: the defaults
    device: str = "auto"
    threads: int = TASK_THREADS


@dataclass
class SessionOutcome:
    """What a task did with a session: ``status`` done (a step ran), skipped (all complete already) or
    failed (``error``: one line; ``detail``: the traceback of an unexpected error)."""

    session: str
    status: str
    error: str = ""
    detail: str = ""
    seconds: float = 0.0
    worker: str = ""
    ran: tuple[str, ...] = ()
    manifest: dict = field(default_factory=dict)
    summary: dict = field(default_factory=dict)


@dataclass
class BatchResult:
    """The outcomes by session name (in the study's order), the workers and the wall time."""

    outcomes: dict[str, SessionOutcome]
    workers: int
    wall_s: float

    def count(self, status: str) -> int:
        return sum(o.status == status for o in self.outcomes.values())


def read_study(study: str | Path) -> list[StudySession]:
    """The sessions of a study folder (each folder below it holding ``manifest.json``, and each cube file
    from another camera, ``_study_cubes``; in path order) or of a CSV (a ``session`` column naming a
    session folder or a cube file; paths relative to the CSV; other columns kept as given)."""
    study = Path(study)
    if study.is_dir():
        found = sorted([p.parent for p in study.rglob("manifest.json")] + _study_cubes(study))
        if not found:
            raise InputError(f"{study}: no sessions (folders holding manifest.json) or cube files in this folder")
        return _distinct_fits([StudySession(p.resolve(), p.name if p == study else p.relative_to(study).as_posix()) for p in found], study)
    if not study.is_file():
        raise InputError(f"{study}: no such study folder or CSV")
    return _distinct_fits(_sessions_of_csv(study), study)


def _distinct_fits(sessions: list[StudySession], source: Path) -> list[StudySession]:
    """``sessions``, refused in one line where two would write one fit folder (``arm.hdr`` beside ``arm.tif``
    or a session ``arm``)."""
    seen: dict[Path, str] = {}
    for s in sessions:
        other = seen.setdefault(fit_dir(s.path), s.name)
        if other != s.name:
            raise InputError(f"{source}: {other} and {s.name} would both be fitted into {fit_dir(s.path)}; rename one")
    return sessions


def _study_cubes(study: Path) -> list[Path]:
    """The cube files of other cameras in a study folder (``formats.foreign.cubes``' suffixes; an ENVI
    cube by its ``.hdr``), not those the commands wrote (inside a ``_calibrated``, ``_reconstruction`` or
    ``_study`` folder) nor inside a session."""
    from ..formats.foreign.cubes import CUBE_READERS  # noqa: PLC0415

    written = (CALIBRATED_SUFFIX, RECONSTRUCTION_SUFFIX, STUDY_SUFFIX)
    if (study / "manifest.json").is_file():
        return []  # the study is one session: its files are its frames

    def among_outputs(path: Path) -> bool:
        folders = path.parents[:len(path.relative_to(study).parts) - 1]  # between the study and the file
        return any(f.name.endswith(written) or (f / "manifest.json").is_file() for f in folders)

    return [p for p in study.rglob("*") if p.suffix.lower() in CUBE_READERS and p.is_file() and not among_outputs(p)
            and not p.name.upper().startswith(REFERENCE_CAPTURES)]


def _sessions_of_csv(path: Path) -> list[StudySession]:
    try:
        reader = csv.DictReader(io.StringIO(path.read_text(encoding="utf-8-sig")))
        columns, rows = reader.fieldnames or [], list(reader)
    except (UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path}: not a readable CSV study list ({exc})") from None
    if not rows or "session" not in columns:
        raise InputError(f"{path}: a study list needs a header with a 'session' column and one row per session")
    clashing = sorted({c for c in columns if columns.count(c) > 1} | {c for c in columns if c in RESERVED_COLUMNS or is_map_column(c)})
    if clashing:
        raise InputError(f"{path}: column(s) {', '.join(clashing)} repeated or reserved for the study table; rename them")
    sessions, seen = [], set()
    for line, row in enumerate(rows, start=2):
        name = (row.get("session") or "").strip()
        if not name or None in row:
            raise InputError(f"{path}, line {line}: " + ("no session given" if not name else "more cells than the header has"))
        if name in seen:
            raise InputError(f"{path}, line {line}: session {name} listed twice")
        seen.add(name)
        folder = (Path(name) if Path(name).is_absolute() else path.parent / name).resolve()  # workers may start elsewhere
        sessions.append(StudySession(folder, name, {k: (v or "").strip() for k, v in row.items() if k != "session"}))
    return sessions


def fit_dir(entry: Path) -> Path:
    """Where an entry's fit goes: ``<SESSION>_reconstruction`` beside a session folder, ``<STEM>_reconstruction``
    beside a cube file (several cubes of one folder each get their own)."""
    entry = Path(entry)
    return entry.parent / f"{entry.stem}{RECONSTRUCTION_SUFFIX}" if is_cube_file(entry) and not entry.is_dir() else reconstruction_dir(entry)


def is_cube_file(path: Path) -> bool:
    """A calibrated cube the study fits without a calibration: ``cube.exr`` or any format of
    ``formats.foreign.cubes`` (ENVI, TIFF, NumPy, HDF5), by its suffix."""
    from ..formats.foreign.cubes import CUBE_READERS  # noqa: PLC0415

    return path.suffix.lower() in (".exr", *CUBE_READERS)


def process_session(session: StudySession, options: BatchOptions) -> SessionOutcome:
    """One task: the session's missing steps, then its row of the study table. Never raises for the
    session's own faults: they are the outcome's ``error``."""
    start = time.perf_counter()
    outcome = SessionOutcome(session.name, "skipped", worker=_worker_name())
    try:
        use_task_allocator()  # a worker started by hand runs with Dask's malloc setting: undo it (allocator.py)
        _task_threads(options)
        outcome.manifest = _manifest_columns(session.path)
        if is_cube_file(session.path):
            outcome.ran = _fit_cube_file(session, options)
        else:
            outcome.ran = _run_steps(session.path, options)
        outcome.status = "done" if outcome.ran else "skipped"
        if (fit_dir(session.path) / "fit.json").is_file():
            outcome.summary = session_summary(fit_dir(session.path))
    except Exception as exc:  # noqa: BLE001 (any fault of one session is its outcome, not the study's end)
        outcome.status, outcome.error = "failed", _one_line(exc)
        if not isinstance(exc, (InputError, OSError)):
            outcome.detail = traceback.format_exc()
    outcome.seconds = time.perf_counter() - start
    return outcome


def _run_steps(session: Path, options: BatchOptions) -> tuple[str, ...]:
    """Calibrate and reconstruct where asked and not complete; the steps that ran. A step without its
    completion marker is run from the start, replacing what an interrupted attempt left (a worker killed
    between moving its products into place and its marker)."""
    from ..calibration import calibrate_session  # noqa: PLC0415
    from ..calibration.pipeline import REPORT_NAME  # noqa: PLC0415
    from ..formats.cube import CUBE_NAME, calibrated_dir  # noqa: PLC0415

    if not session.is_dir():
        raise InputError(f"{session}: no such session folder")
    ran = []
    calibrated = calibrated_dir(session)
    if "calibrate" in options.steps and not (calibrated / REPORT_NAME).is_file():
        calibrate_session(session, calibrated, options.calibration_settings, overwrite=True)  # without its marker: an attempt cut short
        ran.append("calibrate")
    if "reconstruct" in options.steps and (ran or not (reconstruction_dir(session) / "fit.json").is_file()):  # a new cube: a new fit
        from ..reconstruct import load_fit_settings, reconstruct_cube  # noqa: PLC0415

        settings = options.fit_settings or load_fit_settings(None)
        if not (calibrated / CUBE_NAME).is_file():
            raise InputError(f"{session}: no calibrated cube at {calibrated / CUBE_NAME}; add the calibrate step")
        reconstruct_cube(calibrated / CUBE_NAME, reconstruction_dir(session), settings, device=_task_device(options.device),
                         force=True)
        ran.append("reconstruct")
    return tuple(ran)


def _fit_cube_file(entry: StudySession, options: BatchOptions) -> tuple[str, ...]:
    """A cube file of the study fitted into ``fit_dir`` unless its fit is complete; its pixel side from the
    file, or from the study list's ``mm_per_pixel`` column where the file does not say it."""
    from ..reconstruct import load_fit_settings, reconstruct_cube  # noqa: PLC0415

    if not entry.path.is_file():
        raise InputError(f"{entry.path}: no such cube file")
    if "reconstruct" not in options.steps or (fit_dir(entry.path) / "fit.json").is_file():
        return ()
    mm = entry.columns.get("mm_per_pixel") or None
    try:
        mm = None if mm is None else float(mm)
    except ValueError:
        raise InputError(f"{entry.name}: mm_per_pixel {mm!r} is not a number") from None
    reconstruct_cube(entry.path, fit_dir(entry.path), options.fit_settings or load_fit_settings(None),
                     device=_task_device(options.device), force=True, mm_per_pixel=mm)
    return ("reconstruct",)


def _manifest_columns(session: Path) -> dict:
    """Subject, site and date (the capture's day) from the session's manifest; empty when unreadable (the
    steps then say why)."""
    try:
        manifest = json.loads((session / "manifest.json").read_text())
        return {column: str(manifest.get(key, ""))[:10] if column == "date" else str(manifest.get(key, ""))
                for column, key in MANIFEST_COLUMNS.items()}
    except (OSError, ValueError, AttributeError):
        return {}


def _task_threads(options: BatchOptions) -> None:
    from ..formats.threads import choose_threads, use_threads  # noqa: PLC0415

    use_threads(choose_threads(options.threads))


def _worker_name() -> str:
    try:
        from distributed import get_worker  # noqa: PLC0415

        return str(get_worker().name)
    except (ImportError, ValueError):
        return f"pid {os.getpid()}"


def _task_device(device: str) -> str:
    """``device`` as asked; for ``auto`` on a machine with GPUs, the GPU of this worker (worker i takes
    GPU i mod count), else the CPU."""
    import torch  # noqa: PLC0415

    if device != "auto":
        return device
    if not torch.cuda.is_available():
        return "cpu"
    name = _worker_name()
    index = int(name) if name.isdigit() else 0
    return f"cuda:{index % torch.cuda.device_count()}"


class _Ledger:
    """``batch.json``: the latest outcome of every session (an earlier run's kept until this run replaces
    it), rewritten atomically after each one."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.entries: dict[str, dict] = {}
        self.outcomes: dict[str, SessionOutcome] = {}
        try:
            self.entries = json.loads(path.read_text())["sessions"]
        except (OSError, ValueError, KeyError, TypeError):
            pass

    def record(self, outcome: SessionOutcome) -> None:
        self.outcomes[outcome.session] = outcome
        self.entries[outcome.session] = without_nan(asdict(outcome))
        atomic_write(self.path, (json.dumps({"sessions": self.entries}, indent=1, default=str) + "\n").encode())


def run_batch(
    sessions: Sequence[StudySession], options: BatchOptions, out: str | Path, *, client=None, scheduler: str | None = None,
    workers: int | None = None, on_outcome: Callable[[SessionOutcome], None] | None = None,
) -> BatchResult:
    """Run ``process_session`` for every session on Dask and record each outcome in ``out/batch.json`` as
    it arrives. ``client``: a Dask client to use (left open); else ``scheduler``'s address; else a
    ``LocalCluster`` of ``workers`` processes (default: one per GPU, else one per usable core)."""
    from distributed import as_completed  # noqa: PLC0415

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ledger = _Ledger(out / LEDGER_NAME)
    start = time.perf_counter()
    with _dask_client(client, scheduler, workers or default_workers(options.device)) as dask_client:
        futures = {dask_client.submit(process_session, s, options, pure=False): s for s in sessions}
        for future in as_completed(futures):
            outcome = _outcome_of(future, futures[future])
            ledger.record(outcome)
            if on_outcome is not None:
                on_outcome(outcome)
        count = len(dask_client.nthreads())
    ordered = {s.name: ledger.outcomes[s.name] for s in sessions}
    return BatchResult(ordered, count, time.perf_counter() - start)


def _outcome_of(future, session: StudySession) -> SessionOutcome:
    """The task's outcome; a task Dask gave up on (its workers lost too often) as a failed one."""
    try:
        return future.result()
    except Exception as exc:  # noqa: BLE001 (KilledWorker, a worker that cannot unpickle: the session failed)
        return SessionOutcome(session.name, "failed", error=_one_line(exc))


def _one_line(exc: BaseException) -> str:
    """An error as one line: its kind and its message, whitespace folded."""
    return " ".join(f"{type(exc).__name__}: {exc}".split())


def default_workers(device: str = "auto") -> int:
    """One worker per GPU where there are GPUs and the device is not the CPU, else one per usable core."""
    import torch  # noqa: PLC0415

    from ..formats.threads import usable_cpus  # noqa: PLC0415

    return torch.cuda.device_count() if device != "cpu" and torch.cuda.is_available() else usable_cpus()


def local_cluster(workers: int):
    """A ``LocalCluster`` of ``workers`` processes, one task each at a time, without the nanny's malloc setting."""
    import dask  # noqa: PLC0415
    from distributed import LocalCluster  # noqa: PLC0415

    with dask.config.set({f"distributed.nanny.pre-spawn-environ.{k}": v for k, v in WORKER_ENVIRON.items()}):
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                            silence_logs=logging.ERROR)


class _dask_client:
    """The client to run on: the caller's (left open), a scheduler's, or a fresh ``LocalCluster``'s."""

    def __init__(self, client, scheduler: str | None, workers: int | None) -> None:
        self.given, self.scheduler, self.workers = client, scheduler, workers
        self.client = self.cluster = None

    def __enter__(self):
        if self.given is not None:
            return self.given
        from distributed import Client  # noqa: PLC0415

        if self.scheduler is not None:
            try:
                self.client = Client(self.scheduler, timeout="30s")
            except (OSError, ValueError, TypeError) as exc:
                raise InputError(f"--scheduler {self.scheduler}: no Dask scheduler answers there ({exc})") from None
            return self.client
        self.cluster = local_cluster(self.workers)
        try:
            self.client = Client(self.cluster)
        except BaseException:
            self.cluster.close()
            raise
        return self.client

    def __exit__(self, *exc) -> None:
        for part in (self.client, self.cluster):
            if part is not None:
                part.close()


def study_rows(sessions: Sequence[StudySession], outcomes: dict[str, SessionOutcome]) -> list[dict]:
    """The study table's rows: the session's name, its listed columns (the manifest's subject, site and
    date where the list leaves them out or empty; every row holds every column, empty where unknown), its
    outcome, and its maps' statistics."""
    listed = []
    for s in sessions:
        o = outcomes[s.name]
        listed.append({**s.columns, **{k: v for k, v in o.manifest.items() if not s.columns.get(k)}})
    names = list(dict.fromkeys(c for columns in listed for c in columns))
    return [{"session": s.name, **{c: columns.get(c, "") for c in names}, "status": outcomes[s.name].status,
             "error": outcomes[s.name].error, "seconds": round(outcomes[s.name].seconds, 3), **outcomes[s.name].summary}
            for s, columns in zip(sessions, listed)]


def write_study(out: str | Path, sessions: Sequence[StudySession], outcomes: dict[str, SessionOutcome],
                group_by: Sequence[str] = (), figures: bool = True) -> dict[str, Path]:
    """``study.csv``, ``study.json`` and (``figures``) the study's figures in ``out``; their paths by kind."""
    out = Path(out)
    rows = study_rows(sessions, outcomes)
    record = study_record(rows, group_by)
    paths = {"table": write_study_table(out / TABLE_NAME, rows), "record": write_study_json(out / RECORD_NAME, record)}
    if figures:
        from .study_charts import plot_study  # noqa: PLC0415 (matplotlib only when figures are drawn)

        maps = {s.name: fit_dir(s.path) / "maps.exr" for s in sessions if outcomes[s.name].summary}
        paths.update(plot_study(out, rows, record, maps))
    return paths


def default_study_out(study: Path) -> Path:
    """``<STUDY>_study`` beside the study folder or CSV."""
    study = study.resolve()
    return study.parent / f"{study.stem if study.is_file() else study.name}{STUDY_SUFFIX}"
