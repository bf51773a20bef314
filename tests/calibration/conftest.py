"""Synthetic inputs for the calibration tests: perspective-rendered windows and a tiny DNG session.

Scenes are rendered on the skin plane (window side = 1, centred at the origin) through a pinhole camera
tilted 30° about the image x axis, integrated over each pixel by supersampling, blurred by a Gaussian
PSF, vignetted and given shot and read noise, so the true corners and reflectance are known exactly.
Under the window's light the skin darkens towards the tape as the model's renderer shows (see
``render_scene``). The session writes DNGs with pidng (uncompressed, 12 bit, a Bayer cell with
per-position black levels and channel gains) and a manifest with ``formats/manifest.py``.

``build_simulated_session`` makes a session with the acquisition's simulator itself (the default scene,
flash jitter, motion, vignetting, lens blur, noise) at a small geometry, and its noiseless twin.
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from skinlayers.formats.manifest import Exposure, FrameRecord, Manifest, write_manifest
from skinlayers.formats.files import file_sha256, now_iso

# (w, l1, l2) of the skin's darkening near the tape, window sides: two exponentials fitted to the model's
# renderer (Table 2 III interior skin, 7.5 mm window, view 30°) at 430, 550 and 670 nm.
LEAK = {430: (0.94, 0.012, 0.036), 550: (0.69, 0.019, 0.074), 670: (0.40, 0.019, 0.105)}


@dataclass
class Scene:
    """A rendered image (DN) and its truth."""

    image: np.ndarray  # (H, W) float32
    corners: np.ndarray  # (4, 2) true window corners TL, TR, BR, BL, pixel-centre coordinates
    homography: np.ndarray  # plane (X, Y, 1) → image; the window is [-0.5, 0.5]²
    gray_box: tuple[int, int, int, int]  # [x0, y0, x1, y1] of the gray card in this image


def camera_homography(shape, window_px=110.0, angle_deg=30.0, shift_px=(0.0, 0.0), rotation_deg=0.0, distance=8.0):
    """Plane → image homography of a pinhole camera ``distance`` window sides away, tilted ``angle_deg``
    about the image x axis; the subject turned by ``rotation_deg`` in its plane and moved by ``shift_px``."""
    h, w = shape
    th = math.radians(angle_deg)
    f = window_px * distance
    cx, cy = (w - 1) / 2 + shift_px[0], (h - 1) / 2 + shift_px[1]
    cam = np.array(
        [[f, cx * math.sin(th), cx * distance], [0, f * math.cos(th) + cy * math.sin(th), cy * distance], [0, math.sin(th), distance]]
    )
    r = math.radians(rotation_deg)
    return cam @ np.array([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1]])


def skin_texture(x, y, seed=0, contrast=1.0):
    """A smooth skin-like pattern on the plane (window units): waves and freckles, about 1 ± 0.2."""
    rng = np.random.default_rng(seed)
    t = 1.0 + 0.06 * contrast * np.sin(9 * x + 2) * np.cos(7 * y - 1)
    for _ in range(12):
        cx, cy = rng.uniform(-0.45, 0.45, 2)
        s = rng.uniform(0.015, 0.05)
        t -= 0.25 * contrast * rng.uniform(0.3, 1) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
    return t


def skin_reflectance(u, v, level, leak, texture_seed=1, contrast=1.0, slide=(0.0, 0.0)):
    """Skin seen through the window at plane points (u, v): R(e) = level · texture · (1 − ½ (w e^{−e/l1} +
    (1 − w) e^{−e/l2})), e the distance to the nearest edge — half the plateau at the edge (a half-lit
    homogeneous medium), rising inward as the renderer shows. ``slide``: the skin moved under the tape
    (window sides), its texture displaced while the window stays."""
    e = np.clip(np.minimum(0.5 - np.abs(u), 0.5 - np.abs(v)), 0, None)
    w, l1, l2 = leak
    texture = skin_texture(u - slide[0], v - slide[1], texture_seed, contrast)
    return level * texture * (1 - 0.5 * (w * np.exp(-e / l1) + (1 - w) * np.exp(-e / l2)))


def render_scene(
    shape=(300, 400),
    *,
    homography=None,
    skin=0.4,
    tape=0.03,
    background=0.6,
    gray=0.3,
    spectralon=None,
    leak=LEAK[430],
    full_scale_dn=8000.0,
    psf_sigma_px=0.6,
    vignetting=0.3,
    read_noise_dn=6.0,
    gain_e_per_dn=2.0,
    seed=0,
    supersample=4,
    texture_seed=1,
    texture_contrast=1.0,
    gray_box=None,
    slide=(0.0, 0.0),
):
    """Render the bench as the camera sees it (module docstring); ``spectralon``: a reflectance that
    replaces tape and window (a reference frame). Noise off with ``read_noise_dn=0, gain_e_per_dn=0``."""
    import cv2

    h, w = shape
    H = camera_homography(shape) if homography is None else homography
    Hinv = np.linalg.inv(H)
    off = (np.arange(supersample) + 0.5) / supersample - 0.5
    X, Y = np.meshgrid((np.arange(w)[:, None] + off).reshape(-1), (np.arange(h)[:, None] + off).reshape(-1))
    den = Hinv[2, 0] * X + Hinv[2, 1] * Y + Hinv[2, 2]
    u = (Hinv[0, 0] * X + Hinv[0, 1] * Y + Hinv[0, 2]) / den
    v = (Hinv[1, 0] * X + Hinv[1, 1] * Y + Hinv[1, 2]) / den
    on_tape = (np.abs(u) <= 2.5) & (np.abs(v) <= 2.5)
    if spectralon is not None:
        refl = np.where(on_tape, spectralon, background)
    else:
        inside = (np.abs(u) <= 0.5) & (np.abs(v) <= 0.5)
        refl = np.where(on_tape, tape, background)
        refl = np.where(inside, skin_reflectance(u, v, skin, leak, texture_seed, texture_contrast, slide), refl)
    if gray_box is None:
        gx0, gy0 = int(0.04 * w), int(0.7 * h)
        gray_box = (gx0, gy0, gx0 + int(0.12 * w), gy0 + int(0.16 * h))
    in_gray = (X >= gray_box[0] - 0.5) & (X < gray_box[2] - 0.5) & (Y >= gray_box[1] - 0.5) & (Y < gray_box[3] - 0.5)
    refl = np.where(in_gray, gray, refl)
    img = refl.reshape(h, supersample, w, supersample).mean(axis=(1, 3))
    if psf_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), psf_sigma_px)
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
    img = img * (1 - vignetting * r2) * full_scale_dn
    rng = np.random.default_rng(seed)
    if gain_e_per_dn > 0:
        img = rng.poisson(np.clip(img, 0, None) * gain_e_per_dn) / gain_e_per_dn
    if read_noise_dn > 0:
        img = img + rng.normal(0, read_noise_dn, img.shape)
    pts = H @ np.array([[-0.5, 0.5, 0.5, -0.5], [-0.5, -0.5, 0.5, 0.5], [1, 1, 1, 1]])
    return Scene(img.astype(np.float32), (pts[:2] / pts[2]).T, H, tuple(gray_box))


def write_dng(path: Path, data: np.ndarray, *, bits=12, black=(64, 64, 64, 64), white=None, cfa="RGGB") -> Path:
    """An uncompressed DNG of a Bayer mosaic ``data`` (uint16) with per-position black levels (row-major
    over the 2×2 cell) — pidng's RAW2DNG as its own examples use it."""
    from pidng.core import RAW2DNG
    from pidng.defs import CFAPattern, DNGVersion, PhotometricInterpretation
    from pidng.dng import DNGTags, Tag

    h, w = data.shape
    tags = DNGTags()
    tags.set(Tag.ImageWidth, w)
    tags.set(Tag.ImageLength, h)
    tags.set(Tag.TileWidth, w)
    tags.set(Tag.TileLength, h)
    tags.set(Tag.Orientation, 1)
    tags.set(Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array)
    tags.set(Tag.SamplesPerPixel, 1)
    tags.set(Tag.BitsPerSample, bits)
    tags.set(Tag.CFARepeatPatternDim, [2, 2])
    tags.set(Tag.CFAPattern, getattr(CFAPattern, cfa))
    tags.set(Tag.BlackLevelRepeatDim, [2, 2])
    tags.set(Tag.BlackLevel, [int(b) for b in black])
    tags.set(Tag.WhiteLevel, int(white if white is not None else (1 << bits) - 1))
    tags.set(Tag.DNGVersion, DNGVersion.V1_4)
    tags.set(Tag.Make, "skinlayers")
    tags.set(Tag.Model, "calibration test")
    conv = RAW2DNG()
    conv.options(tags, path=str(path.parent), compress=False)
    conv.convert(np.ascontiguousarray(data, dtype=np.uint16), filename=path.stem)
    return path


def mosaic(radiance: np.ndarray, gains=(1.0, 1.0, 1.0, 1.0), black=(64, 64, 64, 64), bits=12, offset=0.0) -> np.ndarray:
    """Photosite DN of a raw-resolution radiance image: per cell position gain and black, plus an
    ``offset`` (DN, scalar or image) the tags do not know; clipped, uint16."""
    out = np.array(radiance, dtype=np.float64)
    for k, (dy, dx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        out[dy::2, dx::2] = out[dy::2, dx::2] * gains[k] + black[k]
    out += offset
    return np.clip(np.round(out), 0, (1 << bits) - 1).astype(np.uint16)


# ---- the tiny session ---------------------------------------------------------------------------

BANDS = (430.0, 550.0, 670.0)
SKIN_LEVEL = {430.0: 0.22, 550.0: 0.35, 670.0: 0.5}
GAINS = {430.0: (0.05, 0.35, 0.35, 1.0), 550.0: (0.15, 1.0, 1.0, 0.2), 670.0: (1.0, 0.12, 0.12, 0.03)}
BLACK = (62, 66, 64, 60)
RAW_SHAPE = (320, 440)
WINDOW_RAW_PX = 120.0
CUBE_PX, RECTIFY_PX = 64, 128
SPECTRALON = {430.0: 0.985, 550.0: 0.99, 670.0: 0.992}
SPECTRALON_FACTOR, SKIN_FACTOR = 1.0527, 1.1
# flash intensity per frame: skin over reference 1.082, 0.931, 1.04 — what the gray card must take out
FLASH = {"reference_430": 0.97, "skin_430": 1.05, "reference_550": 1.02, "skin_550": 0.95, "reference_670": 1.0, "skin_670": 1.04}


@dataclass
class SyntheticSession:
    """A session folder and its truth: reflectance ``(L, CUBE_PX, CUBE_PX)``, the gray card's raw box, the
    window's corners in each skin frame (raw px, TL, TR, BR, BL)."""

    path: Path
    wavelengths: tuple[float, ...]
    truth: np.ndarray
    gray_roi_raw: list[int]
    corners: dict[float, np.ndarray]


def truth_cube(level, leak, n=CUBE_PX, supersample=8):
    """True reflectance averaged over each cube pixel of the window (the skin's own, no polarization)."""
    off = (np.arange(n * supersample) + 0.5) / (n * supersample) - 0.5
    u, v = np.meshgrid(off, off)
    return skin_reflectance(u, v, level, leak).reshape(n, supersample, n, supersample).mean(axis=(1, 3))


def build_session(folder: Path, *, seed=7, dark_offset_dn=40.0, hot_spot=0.3, motion=True, slide=None) -> SyntheticSession:
    """Write a three-band session (black frame, Spectralon reference and skin per band) into ``folder``.

    Every frame carries a stray offset the raw tags' black level does not know (``dark_offset_dn``,
    rising left to right; the black frame measures it), the flash's non-uniformity (``hot_spot``: the
    light rises by this fraction from the left to the right edge) and its intensity per frame (``FLASH``).
    ``slide``: {band: (du, dv)} skin that slid under the tape before that band's frame (window sides).
    """
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    h, w = RAW_SHAPE
    card = [int(0.04 * w) // 2 * 2, int(0.72 * h) // 2 * 2, int(0.16 * w) // 2 * 2, int(0.88 * h) // 2 * 2]
    yy, xx = np.mgrid[0:h, 0:w]
    offset = dark_offset_dn * (0.5 + xx / w)  # stray offset above the tags' black level: only the black frame knows it
    illumination = 1 + hot_spot * (xx / w - 0.5)
    frames, truth, corners = [], [], {}

    def frame(name, role, band, position, radiance, gains):
        raw = mosaic(radiance, gains=gains, black=BLACK, offset=offset)
        write_dng(folder / name, raw, black=BLACK)
        frames.append(
            FrameRecord(
                role=role, band_nm=band, filter_position=position, exposure=Exposure(iso=400, shutter_s=0.01, aperture_f=10),
                file=name, sha256=file_sha256(folder / name), time=now_iso(),
            )
        )

    noise = dict(read_noise_dn=3.0, gain_e_per_dn=4.0)
    frame("dark.dng", "dark", None, 1, rng.normal(0, 3.0, RAW_SHAPE), (1, 1, 1, 1))
    for k, band in enumerate(BANDS):
        gains = GAINS[band]
        f_ref, f_skin = FLASH[f"reference_{band:g}"], FLASH[f"skin_{band:g}"]
        still = camera_homography(RAW_SHAPE, window_px=WINDOW_RAW_PX)
        moved = camera_homography(
            RAW_SHAPE, window_px=WINDOW_RAW_PX,
            shift_px=tuple(rng.uniform(-8, 8, 2)) if motion else (0, 0), rotation_deg=rng.uniform(-1, 1) if motion else 0,
        )
        common = dict(full_scale_dn=2600.0, leak=LEAK[int(band)], seed=seed * 10 + k, gray_box=card, **noise)
        ref = render_scene(RAW_SHAPE, homography=still, spectralon=SPECTRALON[band] * SPECTRALON_FACTOR, **common)
        skin = render_scene(
            RAW_SHAPE, homography=moved, skin=SKIN_LEVEL[band] * SKIN_FACTOR, slide=(slide or {}).get(band, (0.0, 0.0)),
            **{**common, "seed": seed * 10 + k + 5},
        )
        frame(f"reference_{band:g}.dng", "reference", band, k + 2, ref.image * f_ref * illumination, gains)
        frame(f"skin_{band:g}.dng", "skin", band, k + 2, skin.image * f_skin * illumination, gains)
        truth.append(truth_cube(SKIN_LEVEL[band], LEAK[int(band)]))
        corners[band] = skin.corners
    rig = {
        "name": "synthetic test rig",
        "bands": [
            {"wavelength_nm": b, "filter_position": k + 2, "iso": 400, "shutter_s": 0.01, "aperture_f": 10} for k, b in enumerate(BANDS)
        ],
        "camera": {"driver": "simulated", "angle_deg": 30.0},
        "targets": {"spectralon_reflectance": {str(b): v for b, v in SPECTRALON.items()}, "gray_card_reflectance": 0.3},
        "polarization": {"spectralon_factor": SPECTRALON_FACTOR, "skin_factor": SKIN_FACTOR},
        "geometry": {"window_mm": 7.5, "cube_px": CUBE_PX, "rectify_px": RECTIFY_PX, "gray_card_roi_px": card},
    }
    write_manifest(folder, Manifest(status="complete", simulated=True, rig=rig, frames=frames))
    return SyntheticSession(folder, BANDS, np.stack(truth), card, corners)


# ---- sessions of the acquisition's simulator ------------------------------------------------------


@dataclass
class SimulatedSession:
    """A session made by the simulated bench: its folder, the bench (for the true window corners:
    ``bench.window_corners_px(frame.shift_px, frame.rotation_deg)``), the true reflectance ``(L, N, N)``
    from ``truth/reflectance.exr``, and what the bench did for each frame, keyed by (role, band)."""

    path: Path
    bench: object
    wavelengths: tuple[float, ...]
    truth: np.ndarray
    frames: dict


def build_simulated_session(
    folder: Path, *, bands=(430.0, 550.0, 670.0), cube_px=64, rectify_px=128, seed=0, noiseless=False, supersample=8,
    wavelength_samples=1,
) -> SimulatedSession:
    """Capture a session with ``SimulatedBench`` into ``folder`` (the CPU, the rig's exposures for the
    bands, the default scene and simulation settings otherwise) and write its truth.

    ``supersample``: the simulator's samples per raw pixel per axis. Its default is 2; here 8, because
    the test holds corners to 0.3 px and at 2 the finite sampling of the tape's edge alone moved the worst
    corner by 0.30 px (measured at 430 nm; 4 gave 0.34, 8 passes with a margin). ``noiseless``: the same scene, motion and
    flash with the sensor's shot and read noise made negligible (×10⁵ electrons at the same DN), for
    the noise floor. ``wavelength_samples`` 1: the band centre (the truth is made with the same nodes).
    """
    from skinlayers.acquire.hardware.rig import load_rig
    from skinlayers.acquire.session import AutoOperator, run_session
    from skinlayers.acquire.hardware.simdevices import SimulatedCamera, SimulatedWheel
    from skinlayers.acquire.simulator.simulated import SimulatedBench
    from skinlayers.acquire.simulator.simulation_settings import simulation_from_dict
    from skinlayers.formats.exr import read_exr

    by_nm = {b.wavelength_nm: b for b in load_rig().bands}
    rig = load_rig(bands=[by_nm[b].model_dump() for b in bands], geometry={"cube_px": cube_px, "rectify_px": rectify_px},
                   camera={"driver": "simulated"})
    sim = {"filters": {"wavelength_samples": wavelength_samples}, "camera": {"supersample": supersample}}
    bench = SimulatedBench(rig, None, simulation_from_dict(sim), seed=seed, device="cpu")
    if noiseless:
        k, sensor = 1e5, bench.settings.sensor
        sim["sensor"] = {"white_electrons": bench.white_electrons * k, "e_per_dn_iso100": sensor.e_per_dn_iso100 * k,
                         "full_well_e": sensor.full_well_e * k, "read_noise_e": 0.0, "read_noise_dn": 0.0}
        bench = SimulatedBench(rig, None, simulation_from_dict(sim), seed=seed, device="cpu")
    wheel = SimulatedWheel(rig.wheel.position_count, time_scale=0.0)
    run_session(folder, bench.rig_as_used(), wheel, SimulatedCamera(bench, wheel), AutoOperator(bench.set_target), simulated=True)
    bench.write_truth(folder)
    channels, _ = read_exr(folder / "truth" / "reflectance.exr")
    truth = np.stack([channels[f"R_{b:g}"] for b in bands])
    role = {"skin": "skin", "spectralon": "reference"}
    frames = {("dark" if f.band_nm is None else role[f.target], f.band_nm): f for f in bench.frames}
    return SimulatedSession(folder, bench, tuple(bands), truth, frames)


def predicted_noise(session: Path, band: dict, cube_px: int, rectify_px: int, mask: np.ndarray, sensor, seed=0) -> float:
    """The RMS noise a band of the cube carries (reflectance, over ``mask``), predicted from the raw frames
    and the simulator's sensor model (EMVA 1288, ``acquire/simulator/_sensor.py``): each photosite's variance
    μ_e/g² + (σ_e/g)² + σ_DN² + 1/12 in DN², g electrons per DN at the frame's ISO; a superpixel's is the
    sum of its four; the ratio's R² (var S/S² + var F/F²) × the band's scale². A Gaussian field of that
    variance goes through the calibration's own rectification and box filter. ``band``: the band's entry
    of ``calibration.json``; ``sensor``: the simulation's ``SimSensor``. The gray card's noise (a scale
    per band, < 0.1% at full size) is left out."""
    from skinlayers.formats.manifest import read_manifest
    from skinlayers.calibration.raw import read_raw, superpixel
    from skinlayers.calibration.window import box_filter, raw_to_superpixel_xy, rectify

    manifest = read_manifest(session)

    def frame(name):
        record = next(f for f in manifest.frames if f.file == name)
        g = sensor.e_per_dn_iso100 * 100.0 / record.exposure.iso
        values = read_raw(session / name).values
        var = np.clip(values, 0, None) / g + (sensor.read_noise_e / g) ** 2 + sensor.read_noise_dn**2 + 1.0 / 12.0
        return superpixel(values), superpixel(var)

    dark, dark_var = frame(next(f.file for f in manifest.frames if f.role == "dark"))
    (s, s_var), (f, f_var) = frame(band["skin_file"]), frame(band["reference_file"])
    s, f = s - dark, f - dark
    ratio = np.divide(s, f, out=np.zeros_like(s), where=f > 0)
    var = ratio**2 * (np.divide(s_var + dark_var, s**2, out=np.zeros_like(s), where=s > 0)
                      + np.divide(f_var + dark_var, f**2, out=np.zeros_like(f), where=f > 0)) * band["scale"] ** 2
    field = np.random.default_rng(seed).normal(size=var.shape) * np.sqrt(var)
    corners = raw_to_superpixel_xy(np.array(band["window_corners_px"]), band["cell_centroid_px"])
    cube = box_filter(rectify(field.astype(np.float32), corners, rectify_px, "cubic"), rectify_px // cube_px)
    return float(np.sqrt(np.mean(cube[mask] ** 2)))


def tree_hash(folder: Path) -> str:
    """SHA-256 over every path under ``folder`` and every file's bytes."""
    import hashlib

    h = hashlib.sha256()
    for path in sorted(folder.rglob("*")):
        h.update(str(path.relative_to(folder)).encode())
        if path.is_file():
            h.update(path.read_bytes())
    return h.hexdigest()


@pytest.fixture(scope="session")
def synth() -> SimpleNamespace:
    """This module's helpers (``render_scene``, ``write_dng``, ``build_session``, constants) for the tests,
    which cannot import a conftest."""
    return SimpleNamespace(**{k: v for k, v in globals().items() if not k.startswith("_")})


@pytest.fixture(scope="session")
def synthetic_session(tmp_path_factory) -> SyntheticSession:
    """One tiny session, built once; tests that change it work on a copy (``session_copy``)."""
    return build_session(tmp_path_factory.mktemp("session") / "session")


@pytest.fixture
def session_copy(synthetic_session, tmp_path) -> SyntheticSession:
    """A private copy of the synthetic session that a test may break."""
    dest = tmp_path / "session"
    shutil.copytree(synthetic_session.path, dest)
    s = synthetic_session
    return SyntheticSession(dest, s.wavelengths, s.truth, s.gray_roi_raw, s.corners)
