"""The capture session: a black frame, a Spectralon reference per band, then the skin at every band
(DWRR08 §6.1–6.2), driven through the ``FilterWheel`` and ``Camera`` protocols.

Nothing is lost on a fault and nothing is overwritten:

- a new session needs a folder that does not exist or is empty; ``resume=True`` continues the
  session of an existing ``manifest.json`` with the rig recorded there and takes only the frames it
  lacks (frames already taken are checked against their SHA-256 and never taken again);
- each frame is captured to a temporary name in the session folder, renamed to its own name (a name
  already taken gets a ``-retake-N`` suffix instead of replacing anything), and only then recorded in
  the manifest, which is rewritten atomically after every frame — an interruption at any moment
  leaves a consistent, resumable session;
- where a person must act (place the Spectralon target, place the patch) the ``Operator`` is asked;
  ``AutoOperator`` answers at once (``--yes``).
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Protocol

from .hardware.devices import Camera, ExposureSettings, FilterWheel
from ..formats.errors import InputError
from ..formats.files import file_sha256, now_iso
from ..formats.outputs import inside_session
from ..formats.manifest import FrameRecord, Manifest, ManifestError, read_manifest, write_manifest
from .hardware.rig import RigConfig

log = logging.getLogger(__name__)

__all__ = ["AutoOperator", "Operator", "PlannedFrame", "SessionError", "SessionSummary", "plan_session", "run_session"]

PARTIAL_PREFIX = ".partial-"
TARGET_OF_ROLE = {"reference": "spectralon", "skin": "skin"}
INSTRUCTIONS = {
    "spectralon": "Place the Spectralon target where the skin patch will be (it must cover the whole window area).",
    "skin": "Place the skin patch with its black tape window under the camera (gel on, gray card in view).",
}

Progress = Callable[[int, int, str], None]


class SessionError(InputError):
    """A session that cannot start or continue; the message names the folder and the problem."""


@dataclass(frozen=True)
class PlannedFrame:
    """One frame of the protocol: its role, band, wheel position, exposure and file stem."""

    role: str
    band_nm: Optional[float]
    filter_position: int
    exposure: ExposureSettings
    stem: str


class Operator(Protocol):
    """The person at the rig: asked to place a target before the frames that need it."""

    def place(self, target: str, instruction: str) -> None:
        """Return once ``target`` ('spectralon' or 'skin') is in place; raise ``KeyboardInterrupt`` to stop."""
        ...


@dataclass
class AutoOperator:
    """Answers every prompt at once (``--yes``); ``on_place`` is told the target (the simulated bench
    places it)."""

    on_place: Optional[Callable[[str], None]] = None
    placed: list[str] = field(default_factory=list)

    def place(self, target: str, instruction: str) -> None:
        self.placed.append(target)
        if self.on_place is not None:
            self.on_place(target)


@dataclass(frozen=True)
class SessionSummary:
    folder: Path
    frames_total: int
    frames_taken: int
    frames_before: int
    bands_nm: list[float]
    seconds: float
    complete: bool


def _band_stem(role: str, band_nm: float) -> str:
    return f"{role}_{band_nm:g}nm".replace(".", "p")  # no dot: the camera appends its raw suffix


def plan_session(rig: RigConfig) -> list[PlannedFrame]:
    """The protocol: one black frame through the opaque slot (at the highest ISO of the rig, the
    noisiest exposure used; the black level itself comes from each raw file), then a Spectralon
    reference per band, then the skin per band, each at its band's exposure."""
    def exposure(b) -> ExposureSettings:
        return ExposureSettings(b.iso, b.shutter_s, b.aperture_f)

    darkest = max(rig.bands, key=lambda b: b.iso)
    frames = [PlannedFrame("dark", None, rig.wheel.dark_position, exposure(darkest), "dark")]
    for role in ("reference", "skin"):
        frames += [PlannedFrame(role, b.wavelength_nm, b.filter_position, exposure(b), _band_stem(role, b.wavelength_nm))
                   for b in rig.bands]
    return frames


def _start(folder: Path, rig: RigConfig, resume: bool, info: dict) -> Manifest:
    if resume:
        try:
            manifest = read_manifest(folder)
        except ManifestError as exc:
            raise SessionError(f"cannot resume: {exc}") from None
        recorded = manifest.rig_config()
        if recorded.model_dump() != rig.model_dump():
            raise SessionError(f"{folder}: the session was started with another rig ({recorded.name!r}); "
                               "resume it with the rig recorded in its manifest")
        for f in manifest.frames:
            path = folder / f.file
            if not path.is_file():
                raise SessionError(f"{folder}: frame file {f.file} named in the manifest is missing")
            if file_sha256(path) != f.sha256:
                raise SessionError(f"{folder}: frame file {f.file} has changed since it was captured (SHA-256 differs)")
        return manifest
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise SessionError(f"{folder}: exists and is not empty; a session is never overwritten "
                           "(choose a new folder, or --resume to continue the session in it)")
    outer = inside_session(folder.parent)
    if outer is not None:
        raise SessionError(f"{folder}: lies inside the session {outer}, which is never written to; choose a folder outside it")
    folder.mkdir(parents=True, exist_ok=True)
    manifest = Manifest(rig=rig.model_dump(mode="json"), **info)
    write_manifest(folder, manifest)
    return manifest


def _free_name(folder: Path, name: str) -> str:
    if not (folder / name).exists():
        return name
    stem, suffix = os.path.splitext(name)
    n = 1
    while (folder / f"{stem}-retake-{n}{suffix}").exists():
        n += 1
    return f"{stem}-retake-{n}{suffix}"


def _capture_frame(folder: Path, wheel: FilterWheel, camera: Camera, p: PlannedFrame) -> FrameRecord:
    """One planned frame: the wheel moved, the camera set and fired into a temporary file, which is
    renamed into place only once whole (removed if the capture fails); its record for the manifest."""
    wheel.move_to(p.filter_position)
    got = camera.configure(p.exposure)
    partial = folder / f"{PARTIAL_PREFIX}{p.stem}"
    written: Optional[Path] = None
    try:
        written = Path(camera.capture(partial))
        name = _free_name(folder, p.stem + written.suffix.lower())
        os.replace(written, folder / name)
        written = None
    finally:
        if written is not None and written.exists():
            written.unlink()
    log.info("%s frame%s: filter %d, %s → %s", p.role, f" {p.band_nm:g} nm" if p.band_nm is not None else "",
             p.filter_position, got.as_dict(), name)
    return FrameRecord(
        role=p.role, band_nm=p.band_nm, filter_position=p.filter_position, exposure=got.as_dict(),
        file=name, sha256=file_sha256(folder / name), time=now_iso(),
    )


def run_session(
    folder: str | Path,
    rig: RigConfig,
    wheel: FilterWheel,
    camera: Camera,
    operator: Operator,
    *,
    resume: bool = False,
    subject: str = "",
    site: str = "",
    operator_name: str = "",
    simulated: bool = False,
    notes: Optional[dict] = None,
    software_version: str = "unknown",
    progress: Optional[Progress] = None,
) -> SessionSummary:
    """Capture (or continue) a session in ``folder``; returns what was done.

    Device errors (``WheelError``, ``CameraError``) and ``KeyboardInterrupt`` propagate after the
    frame in flight is discarded; every frame recorded before stays recorded.
    """
    folder = Path(folder)
    info = dict(subject=subject, site=site, operator=operator_name, simulated=simulated,
                notes=notes or {}, software_version=software_version)
    manifest = _start(folder, rig, resume, info)
    for stale in folder.glob(PARTIAL_PREFIX + "*"):
        stale.unlink()  # our own temporary file of a frame that was never recorded
    plan = plan_session(rig)
    before = len(manifest.frames)
    t0 = time.perf_counter()
    target: Optional[str] = None
    done = sum(1 for p in plan if manifest.frame(p.role, p.band_nm) is not None)
    if progress:
        progress(done, len(plan), "starting")
    for p in plan:
        if manifest.frame(p.role, p.band_nm) is not None:
            continue
        needed = TARGET_OF_ROLE.get(p.role)
        if needed is not None and needed != target:
            operator.place(needed, INSTRUCTIONS[needed])
            target = needed
        label = "black frame" if p.role == "dark" else f"{p.role} {p.band_nm:g} nm"
        if progress:
            progress(done, len(plan), label)
        manifest.frames.append(_capture_frame(folder, wheel, camera, p))
        write_manifest(folder, manifest)
        done += 1
        if progress:
            progress(done, len(plan), label)
    manifest.status = "complete"
    write_manifest(folder, manifest)
    return SessionSummary(folder, len(plan), len(manifest.frames) - before, before, rig.wavelengths_nm,
                          time.perf_counter() - t0, True)
