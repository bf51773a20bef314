"""``calibrate_session``: a session folder → ``cube.exr``, ``calibration.json`` and a contact sheet.

The chain (DWRR08 §6.1–6.2, §6.4; the box filter of §7.2), one named step each: read and check the manifest and every frame's checksum; decode the black
frame and, band by band, the Spectralon reference and the skin frame into 2×2 superpixels; subtract
the black frame; divide the skin by the reference at the same camera pixels (the flat field); find the
window in that ratio — the reflectance, flat across the frame, so the tape/skin contrast is the same
at every band and every place — and scale by the gray card, the Spectralon's certified reflectance and
the polarization factors; rectify the window to ``rectify_px``²; measure the bands' residual shifts
against the middle one (ECC) and apply only those beyond ``align_min_shift_px`` (each window is cut
from its own frame, which registers the bands better than ECC can measure them); box-filter to
``cube_px``². Nothing is written until everything is computed, and nothing is ever written into the
session folder. Every error names the frame at fault: its file and what it is (``skin frame, 430 nm``).

Output (default folder: ``<session>_calibrated`` beside the session, so the session stays exactly as
captured — checksums, resumable capture, read-only archives):

- ``cube.exr``: ``R_<nm>`` per band and ``mask`` (``formats/cube.py``); its header holds each band's
  filter width and the camera angle from the rig, the pixel size and the provenance, and a record of the
  window corners per band (raw px), alignment shifts and settings;
- ``calibration.json``: per band exposure, factors (flash, exposure, Spectralon, polarization),
  gray-card levels, window, alignment shift, SNR estimate, saturated and under-exposed fractions; flags;
  time per stage; the settings;
- ``contact_sheet.png`` (``report.py``).
"""

from __future__ import annotations

import logging
import json
import math
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Optional

import cv2
import numpy as np
import torch

from ..formats.cube import CUBE_NAME, Cube, CubeHeader, Provenance, calibrated_dir, write_cube
from ..formats.files import atomic_write, now_iso
from ..formats.manifest import read_manifest
from ..formats.outputs import Staging, check_outputs, claim_outputs
from ..formats.resources import require_memory
from ..formats.rig import RigConfig
from ..formats.version import software_version
from .align import align_bands, apply_alignment
from .checks import (BandFrames, Flag, alignment_flags, card_spectrum_flags, check_reference, exposure_flags, gray_card_flags,
                     select_frames, verify_files)
from .corrections import band_factors, gray_card_level, reflectance_ratio, roi_to_superpixels, subtract_dark
from .errors import CalibrationError
from .raw import RawImage, cell_centroid, cell_weights, read_raw
from .report import Thumbnail, band_caption, band_snr, thumbnail, write_contact_sheet
from .settings import CalibrationSettings
from .window import box_filter, find_window, rectify, superpixel_to_raw_xy, window_interior
from ..formats.threads import library_threads

log = logging.getLogger(__name__)

__all__ = ["CalibrationResult", "ProgressFn", "calibrate_session", "default_out_dir"]

ProgressFn = Callable[[int, int, str], None]
"""``progress(done, total, message)``, called after each step."""

REPORT_NAME, SHEET_NAME = "calibration.json", "contact_sheet.png"
#: What a calibration writes; ``calibration.json`` last: its presence marks a complete calibration.
OUTPUT_NAMES = (CUBE_NAME, SHEET_NAME, REPORT_NAME)
#: A rectified pixel counts as valid in the cube when this share of it came from valid superpixels.
_VALID_SHARE = 0.999


@dataclass
class CalibrationResult:
    """What ``calibrate_session`` made: the cube (as written), where, the report's content, the flags
    and the seconds spent per stage."""

    cube: Cube
    out_dir: Path
    cube_path: Path
    report_path: Path
    contact_sheet_path: Path
    report: dict
    flags: list[Flag] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=dict)


@dataclass
class _Inputs:
    """The verified session: its rig, the frames to use and their files, the output folder."""

    session: Path
    rig: RigConfig
    out: Path
    dark_file: Optional[str]
    bands: list[BandFrames]
    paths: dict[str, Path]
    roi: Optional[list[int]]
    reference_index: int


@dataclass
class _Band:
    """One band calibrated: rectified reflectance and validity ``(rectify_px, rectify_px)``, its flags,
    its thumbnail and its entry in ``calibration.json``."""

    rectified: np.ndarray
    valid: np.ndarray
    flags: list[Flag]
    thumb: Thumbnail
    entry: dict


@dataclass
class _Alignment:
    """Each band's measured shift (cube px), ECC correlation and whether the shift was applied."""

    shifts: np.ndarray
    correlation: np.ndarray
    applied: np.ndarray
    flags: list[Flag]


def default_out_dir(session: str | Path) -> Path:
    """``<session>_calibrated`` beside the session folder."""
    return calibrated_dir(session)


def calibrate_session(
    session_dir: str | Path,
    out_dir: str | Path | None = None,
    settings: Optional[CalibrationSettings] = None,
    progress: Optional[ProgressFn] = None,
    *,
    overwrite: bool = False,
) -> CalibrationResult:
    """Calibrate a session folder into a reflectance cube (see the module docstring).

    ``out_dir``: where to write (default ``default_out_dir(session_dir)``; never inside the session).
    ``overwrite``: replace an earlier calibration there. Raises the errors of ``checks.py`` (ValueError
    or OSError subclasses, one line each); problems that leave the cube usable become flags.
    """
    settings = settings or CalibrationSettings()
    library_threads()  # SKINLAYERS_THREADS, where set (formats/threads.py)
    timings: dict[str, float] = {}
    clock = _stage_clock(timings)
    with clock("verify"):
        inputs = _verify(Path(session_dir).resolve(), out_dir, overwrite, settings)
    require_memory(_calibration_bytes(inputs), f"calibrating {len(inputs.bands)} bands at {inputs.rig.geometry.rectify_px}² px",
                   "Lower the rig's geometry.rectify_px (and cube_px).")
    with claim_outputs(inputs.out, OUTPUT_NAMES, force=overwrite, marker=REPORT_NAME, what="calibration") as staging:
        return _calibrate(inputs, settings, staging, progress, timings, clock)


def _calibrate(inputs: _Inputs, settings: CalibrationSettings, staging: Staging, progress, timings, clock) -> CalibrationResult:
    """The calibration itself, into the claimed folder's staging area (see ``calibrate_session``)."""
    total = len(inputs.bands) + 3
    _report(progress, 1, total, "frames verified")
    with clock("decode"):
        dark = _decode(inputs.paths[inputs.dark_file], "black frame", settings) if inputs.dark_file is not None else None
    dark_sp = dark.superpixel() if dark is not None else None
    bands = []
    for k, frames in enumerate(inputs.bands):
        bands.append(_calibrate_band(frames, dark, dark_sp, inputs, settings, clock))
        entry = bands[-1].entry
        log.info("%g nm: window corners %s px, edge rms %.2f px, saturated %.1f%%, flags %s", frames.wavelength_nm,
                 [[round(v) for v in c] for c in entry["window_corners_px"]], entry["window_edge_rms_px"],
                 100 * entry["saturated_fraction"], [f.code for f in bands[-1].flags] or "none")
        _report(progress, 2 + k, total, f"{frames.wavelength_nm:g} nm calibrated")
    stack, valid = np.stack([b.rectified for b in bands]), np.stack([b.valid for b in bands])
    with clock("align"):
        stack, valid, alignment = _align(stack, valid, inputs, settings)
    _report(progress, total - 1, total, "bands aligned")
    with clock("rectify"):
        cube_r, mask = _to_cube_grid(stack, valid, inputs.rig, settings)
    entries = _band_entries(bands, alignment, cube_r, mask)
    flags = [f for b in bands for f in b.flags] + alignment.flags
    flags += card_spectrum_flags([b.wavelength_nm for b in inputs.bands], [b.entry["gray_card_reading"] for b in bands], settings)
    cube = Cube(torch.from_numpy(cube_r), torch.from_numpy(mask), _cube_header(inputs, entries, settings))
    report = _calibration_report(inputs, entries, flags, mask, settings)
    with clock("write"):
        _write_images(cube, bands, entries, flags, inputs, staging)
    report["timings_s"] = {**{k: round(v, 4) for k, v in timings.items()}, "total": round(sum(timings.values()), 4)}
    atomic_write(staging.path(REPORT_NAME), (json.dumps(report, indent=2, allow_nan=False) + "\n").encode(), prefix=".calibration-")
    _report(progress, total, total, f"written to {inputs.out}")
    out = inputs.out
    return CalibrationResult(cube, out, out / CUBE_NAME, out / REPORT_NAME, out / SHEET_NAME, report, flags, report["timings_s"])


def _verify(session: Path, out_dir: str | Path | None, overwrite: bool, settings: CalibrationSettings) -> _Inputs:
    """The manifest, its rig and every frame checked; the output folder chosen."""
    manifest = read_manifest(session)
    rig = manifest.rig_config()
    geo = rig.geometry
    if geo.rectify_px % geo.cube_px:
        raise CalibrationError(f"rig geometry: rectify_px {geo.rectify_px} is not a multiple of cube_px {geo.cube_px}")
    out = default_out_dir(session) if out_dir is None else Path(out_dir).resolve()
    check_outputs(out, OUTPUT_NAMES, force=overwrite, what="calibration")  # before the frames are hashed
    dark_record, bands = select_frames(manifest, rig, settings.dark_frame)
    paths = verify_files(session, manifest.frames)
    roi = settings.gray_card_roi_px or geo.gray_card_roi_px
    if settings.gray_card and roi is None:
        raise CalibrationError(
            f"{session}: the rig in the manifest has no geometry.gray_card_roi_px; give the card's region "
            "(calibration setting gray_card_roi_px, or --gray-card-roi x0,y0,x1,y1) or switch the gray card off (--no-gray-card)"
        )
    wavelengths = [b.wavelength_nm for b in bands]
    dark_file = dark_record.file if settings.dark_frame else None
    return _Inputs(session, rig, out, dark_file, bands, paths, roi, _reference_band(wavelengths, settings.align_reference_nm))


def _calibrate_band(
    bf: BandFrames, dark: Optional[RawImage], dark_sp: Optional[np.ndarray], inputs: _Inputs, settings: CalibrationSettings, clock,
) -> _Band:
    """Decode a band's reference and skin frames, correct them, find the window, rectify it (``dark_sp``:
    the black frame's superpixels)."""
    w = bf.wavelength_nm
    with clock("decode"):
        ref, skin, ref_name, skin_name = _decoded_pair(bf, dark, inputs, settings)
    with clock("corrections"):
        c = _corrected(bf, ref, skin, dark, dark_sp, inputs, settings, ref_name, skin_name)
    with clock("window"):
        win = find_window(
            c.ratio, exclude=c.card, min_area_fraction=settings.window_min_area_fraction,
            max_ring_ratio=settings.window_max_ring_ratio, edge_model=settings.window_edge_model,
            cell_weights=c.weights, name=skin_name,
        )
    with clock("corrections"):
        inside = np.zeros(c.s_img.shape, np.uint8)
        cv2.fillConvexPoly(inside, np.round(win.corners * 16).astype(np.int32), 1, shift=4)
        inside = inside.astype(bool)
        sat = c.sat_skin | c.sat_ref
        if settings.flat_field:
            refl, defined = c.ratio * np.float32(c.factors.scale), c.defined
        else:
            refl, defined = reflectance_ratio(c.s_img, c.f_img, c.factors.scale, float(np.median(c.f_img[inside])))
        valid = defined & ~sat & ~c.under
        # the card read against the Spectralon in the reference frame (checks.card_spectrum_flags)
        card_reading = (c.gray_ref / float(np.median(c.f_img[inside])) * c.factors.spectralon_reflectance
                        if c.gray_ref is not None else None)
        interior = window_interior(inside, win.blur_px)
        sat_fraction = float(np.mean(sat[interior]))
        under_fraction = float(np.mean((c.under & ~sat)[interior]))
    with clock("rectify"):
        rectified = rectify(refl, win.corners, inputs.rig.geometry.rectify_px, settings.interpolation)
        valid_rect = rectify(valid.astype(np.float32), win.corners, inputs.rig.geometry.rectify_px, "linear")
    flags = _band_flags(w, c, win, sat_fraction, under_fraction, settings)
    entry = {
        "wavelength_nm": w,
        "skin_file": bf.skin.file,
        "reference_file": bf.reference.file,
        "exposure": {"skin": bf.skin.exposure.model_dump(), "reference": bf.reference.exposure.model_dump()},
        **c.factors.as_dict(),
        "gray_card_dn": None if c.gray_ref is None else {"reference": c.gray_ref, "skin": c.gray_skin},
        "gray_card_reading": _finite(card_reading) if card_reading is not None else None,
        "window_corners_px": superpixel_to_raw_xy(win.corners, c.centroid).tolist(),
        "cell_centroid_px": list(c.centroid),
        "window_edge_rms_px": 2.0 * win.edge_rms_px,
        "window_blur_px": _finite(2.0 * win.blur_px),
        "saturated_fraction": sat_fraction,
        "underexposed_fraction": under_fraction,
    }
    return _Band(rectified, valid_rect, flags, thumbnail(c.s_img, win.corners, c.box), entry)


def _decoded_pair(bf: BandFrames, dark: Optional[RawImage], inputs: _Inputs, settings: CalibrationSettings):
    """The band's reference and skin frames decoded, their sizes checked against each other and the
    black frame; returns them with the names errors give them."""
    w = bf.wavelength_nm
    ref = _decode(inputs.paths[bf.reference.file], f"reference frame, {w:g} nm", settings)
    skin = _decode(inputs.paths[bf.skin.file], f"skin frame, {w:g} nm", settings)
    skin_name, ref_name = f"{skin.path} (skin frame, {w:g} nm)", f"{ref.path} (reference frame, {w:g} nm)"
    for frame, name in ((ref, ref_name), (skin, skin_name)):
        if dark is not None and frame.shape != dark.shape:
            raise CalibrationError(f"{name}: {frame.shape[1]}×{frame.shape[0]} px, the black frame {dark.shape[1]}×{dark.shape[0]}")
    if ref.shape != skin.shape:
        raise CalibrationError(f"{skin_name}: {skin.shape[1]}×{skin.shape[0]} px, its reference {ref.shape[1]}×{ref.shape[0]}")
    return ref, skin, ref_name, skin_name


@dataclass
class _Corrected:
    """A band's frames corrected, in superpixels: skin and reference less the black frame, the cells'
    weights and centroid, saturation and under-exposure masks, the gray card's box and levels, the
    band's factors and the skin-over-reference ratio (with where it is defined)."""

    s_img: np.ndarray
    f_img: np.ndarray
    weights: np.ndarray
    centroid: tuple
    sat_skin: np.ndarray
    sat_ref: np.ndarray
    under: np.ndarray
    box: object
    card: list
    gray_ref: Optional[float]
    gray_skin: Optional[float]
    factors: object
    ratio: np.ndarray
    defined: np.ndarray


def _corrected(bf: BandFrames, ref: RawImage, skin: RawImage, dark: Optional[RawImage], dark_sp: Optional[np.ndarray],
               inputs: _Inputs, settings: CalibrationSettings, ref_name: str, skin_name: str) -> _Corrected:
    """Black frame subtracted, exposure masks, the reference and gray card checked, the band's factors,
    and the ratio of skin over reference at the same camera pixels."""
    roi = inputs.roi
    s_img = subtract_dark(skin.superpixel(), dark_sp)
    f_img = subtract_dark(ref.superpixel(), dark_sp)
    flat = ref.values if dark is None else ref.values - dark.values
    sat_skin, sat_ref = skin.superpixel_saturated(), ref.superpixel_saturated()
    low = settings.underexposure_level * 4.0
    under = (s_img < low * skin.full_scale_dn) | (f_img < low * ref.full_scale_dn)
    box = roi_to_superpixels(roi, s_img.shape, settings.gray_card_inset) if roi is not None else None
    card = [roi_to_superpixels(roi, s_img.shape)] if roi is not None else []
    check_reference(s_img, f_img, card, ref_name)
    gray_ref = gray_skin = None
    if settings.gray_card:
        gray_ref = gray_card_level(f_img, box, sat_ref, ref_name)
        gray_skin = gray_card_level(s_img, box, sat_skin, skin_name)
    factors = band_factors(
        settings, inputs.rig, bf.wavelength_nm, gray_reference=gray_ref, gray_skin=gray_skin,
        exposure_reference=bf.reference.exposure, exposure_skin=bf.skin.exposure,
    )
    # skin over reference at the same camera pixels: the reflectance up to the band's scalar
    # factors, flat across the frame (vignetting and the flash's shape cancel)
    ratio, defined = reflectance_ratio(s_img, f_img, 1.0)
    return _Corrected(s_img, f_img, cell_weights(flat), cell_centroid(flat), sat_skin, sat_ref, under, box, card,
                      gray_ref, gray_skin, factors, ratio, defined)


def _band_flags(w: float, c: _Corrected, win, sat_fraction: float, under_fraction: float,
                settings: CalibrationSettings) -> list[Flag]:
    """The band's exposure, gray card and window-edge flags."""
    flags = exposure_flags(w, sat_fraction, under_fraction, settings)
    if settings.gray_card:
        flags += gray_card_flags(w, c.factors.flash_factor, settings)
    if settings.window_edge_model and win.model_sides < 4:
        failed = 4 - win.model_sides
        flags.append(Flag("edge_model", w, f"{w:g} nm: edge model failed on {failed} window side(s); derivative peaks used", failed))
    return flags


def _align(stack: np.ndarray, valid: np.ndarray, inputs: _Inputs, settings: CalibrationSettings):
    """Measure the bands' shifts against the reference band; apply those beyond ``align_min_shift_px``."""
    geo, n = inputs.rig.geometry, stack.shape[0]
    per_rect = geo.cube_px / geo.rectify_px
    alignment = _Alignment(np.zeros((n, 2)), np.ones(n), np.zeros(n, bool), [])
    if not settings.align_bands or n < 2:
        return stack, valid, alignment
    al = align_bands(
        stack, inputs.reference_index, valid=valid >= _VALID_SHARE, motion=settings.align_motion, border=settings.align_border,
        max_shift_px=settings.max_alignment_px / per_rect,
    )
    shifts = al.shifts_px * per_rect
    # Each band's window is cut from its own frame, which registers the bands to the corners'
    # accuracy; ECC across bands of different contrast is biased by more than that (both:
    # docs/calibration.md, "From calibration/align.py"), so only a larger shift — skin that slid under
    # the tape — is applied.
    applied = al.converged & (np.hypot(shifts[:, 0], shifts[:, 1]) >= settings.align_min_shift_px)
    flags = alignment_flags([b.wavelength_nm for b in inputs.bands], shifts, al.converged, settings)
    if applied.any():
        al = replace(al, warps=np.where(applied[:, None, None], al.warps, np.eye(2, 3, dtype=np.float32)))
        stack = apply_alignment(stack, al, settings.interpolation)
        valid = apply_alignment(valid, al, "linear")
    return stack, valid, _Alignment(shifts, al.correlation, applied, flags)


def _to_cube_grid(stack: np.ndarray, valid: np.ndarray, rig: RigConfig, settings: CalibrationSettings) -> tuple[np.ndarray, np.ndarray]:
    """Box-filter the rectified bands to ``cube_px``²; the mask: valid in every band, off the edge margin."""
    factor = rig.geometry.rectify_px // rig.geometry.cube_px
    cube_r = box_filter(stack, factor).astype(np.float32)
    mask = (box_filter(valid, factor) >= _VALID_SHARE).all(axis=0)
    m = settings.edge_margin_px
    if m:
        mask[:m], mask[-m:], mask[:, :m], mask[:, -m:] = False, False, False, False
    return cube_r, mask


def _band_entries(bands: list[_Band], alignment: _Alignment, cube_r: np.ndarray, mask: np.ndarray) -> list[dict]:
    """Each band's ``calibration.json`` entry, completed with its alignment and the cube's statistics."""
    entries = []
    for k, band in enumerate(bands):
        entry = dict(band.entry)
        entry["alignment_shift_px"] = [_finite(v) for v in alignment.shifts[k]]
        entry["alignment_applied"] = bool(alignment.applied[k])
        entry["alignment_correlation"] = _finite(alignment.correlation[k])
        entry["snr"] = _finite(band_snr(cube_r[k], mask))
        entry["median_reflectance"] = _finite(float(np.median(cube_r[k][mask])) if mask.any() else float("nan"))
        entries.append(entry)
    return entries


def _cube_header(inputs: _Inputs, entries: list[dict], settings: CalibrationSettings) -> CubeHeader:
    """The cube's header: the bands, their filters' widths and the camera angle from the rig."""
    rig, geo = inputs.rig, inputs.rig.geometry
    wavelengths = [b.wavelength_nm for b in inputs.bands]
    by_band = lambda key: {f"{e['wavelength_nm']:g}": e[key] for e in entries}  # noqa: E731
    return CubeHeader(
        wavelengths_nm=wavelengths,
        band_fwhm_nm=[rig.band(w).fwhm_nm for w in wavelengths],
        camera_angle_deg=rig.camera.angle_deg,
        mm_per_pixel=geo.window_mm / geo.cube_px,
        provenance=Provenance(session=str(inputs.session), made_by="skinlayers calibrate", created=now_iso(), rig=rig.name),
        calibration={
            "report": REPORT_NAME,
            "window_mm": geo.window_mm,
            "window_corners_px": by_band("window_corners_px"),
            "alignment_shift_px": by_band("alignment_shift_px"),
            "alignment_applied": by_band("alignment_applied"),
            "reference_band_nm": wavelengths[inputs.reference_index],
            "settings": settings.model_dump(mode="json"),
        },
    )


def _calibration_report(inputs: _Inputs, entries: list[dict], flags: list[Flag], mask: np.ndarray, settings: CalibrationSettings) -> dict:
    """``calibration.json``'s content (the stage times are added once everything is written)."""
    rig, geo = inputs.rig, inputs.rig.geometry
    return {
        "session": str(inputs.session),
        "software_version": software_version(),
        "created": now_iso(),
        "rig": rig.name,
        "camera_angle_deg": rig.camera.angle_deg,
        "window_mm": geo.window_mm,
        "rectify_px": geo.rectify_px,
        "cube_px": geo.cube_px,
        "mm_per_pixel": geo.window_mm / geo.cube_px,
        "reference_band_nm": inputs.bands[inputs.reference_index].wavelength_nm,
        "mask_valid_fraction": float(mask.mean()),
        "bands": entries,
        "flags": [f.as_dict() for f in flags],
        "settings": settings.model_dump(mode="json"),
        "outputs": {"cube": CUBE_NAME, "contact_sheet": SHEET_NAME},
    }


def _write_images(cube: Cube, bands: list[_Band], entries: list[dict], flags: list[Flag], inputs: _Inputs, staging: Staging) -> None:
    """``cube.exr`` and ``contact_sheet.png`` into the staging area."""
    wavelengths = cube.header.wavelengths_nm
    write_cube(staging.path(CUBE_NAME), cube)
    cube_r, mask = cube.reflectance.numpy(), cube.mask.numpy()
    write_contact_sheet(
        staging.path(SHEET_NAME), wavelengths, [b.thumb for b in bands], cube_r, mask,
        [band_caption(e, k == inputs.reference_index, [f.code for f in flags if f.band_nm == w]) for k, (e, w) in enumerate(zip(entries, wavelengths))],
        [any(f.band_nm == w for f in flags) for w in wavelengths],
        f"{inputs.session.name}: {len(bands)} bands, {len(flags)} flag(s), {mask.mean():.0%} of the window valid",
    )


def _calibration_bytes(inputs: _Inputs) -> float:
    """Peak memory of the calibration: the rectified reflectance and validity of every band (float32),
    twice over while they are aligned, and three decoded raw frames of the camera's size."""
    rect = inputs.rig.geometry.rectify_px ** 2 * len(inputs.bands) * 4 * 2 * 2
    raw = sum(p.stat().st_size for p in list(inputs.paths.values())[:3]) * 12  # 16-bit DNG → float32 values, masks
    return float(rect + raw)


def _decode(path: Path, label: str, settings: CalibrationSettings) -> RawImage:
    return read_raw(path, settings.saturation_margin, label=label)


def _reference_band(wavelengths: list[float], chosen: Optional[float]) -> int:
    if chosen is None:
        return len(wavelengths) // 2
    for k, w in enumerate(wavelengths):
        if abs(w - chosen) < 1e-6:
            return k
    raise CalibrationError(f"align_reference_nm {chosen:g} is not a band of the rig ({', '.join(f'{w:g}' for w in wavelengths)})")


def _finite(value) -> Optional[float]:
    value = float(value)
    return value if math.isfinite(value) else None


def _report(progress: Optional[ProgressFn], done: int, total: int, message: str) -> None:
    if progress is not None:
        progress(done, total, message)


def _stage_clock(timings: dict[str, float]):
    @contextmanager
    def clock(stage: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            timings[stage] = timings.get(stage, 0.0) + time.perf_counter() - start

    return clock
