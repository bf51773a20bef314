"""Synthetic cubes and their fits, built once per test session and shared by the reconstruction tests.

The cubes come from ``synthetic_cubes.py`` (higher fidelity than the fit: twice finer grid, 5-point
band integration, more series terms, real occluded skin, a wider border, camera-like noise). The
default run uses 24×24 cubes rendered with the pyramid blur so that the folder stays near a minute
here; the slow checks use the exact FFT blur and larger cubes.

Noise: ``noise=0.25`` of ``synthetic_cubes``' camera (σ ≈ 0.06% reflectance per 24² pixel). A camera
whose 256² cube has σ ≈ 0.25% gives a 24² cube of the same window σ ≈ 0.025% (each pixel averages
(256/24)² of them), so this is 2.5× noisier than physics asks; at the full 0.25% the per-pixel error
of C_hd reaches 22% (measured; the report explains why).
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
from pathlib import Path

# OpenMP threads that spin while waiting burn the shared cores when other processes run: a 24² fit
# measured 87 s of CPU with spinning threads against 6 s without (see the report). Effective only when
# torch's OpenMP starts after this line (running this folder alone).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import pytest

_PATH = Path(__file__).resolve().with_name("synthetic_cubes.py")


def load_synthetic():
    """The ``synthetic_cubes`` module, loaded by path (test folders are not packages)."""
    name = "skinlayers_tests_synthetic_cubes"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, _PATH)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


#: The small cube's model: the default, but carotene per pixel. Its noise (σ ≈ 0.06%) is a tenth of the rig's
#: session cube, and the data hold C_bc per pixel: measured on it, per pixel C_hd 6.8%, C_m 2.4%; one C_bc
#: for the patch (the default, for the rig's noise) C_hd 11% (the truth's C_bc varies ±30% over 1.5 mm).
SMALL_FIT = {"map_cell_mm": {"C_bc": 0.0}}


class _RenderedOnce:
    """``synthetic_cubes`` whose ``make_cube`` renders each cube (its arguments) once per test run: xdist's
    workers, and the files that ask for the same cube, read it from one file (written whole, under a
    lock, by whichever asks first). Each call returns its own copy."""

    def __init__(self, module, folder: Path) -> None:
        self._module, self._folder = module, folder

    def __getattr__(self, name: str):
        return getattr(self._module, name)

    def make_cube(self, *args, **kwargs):
        import torch
        from filelock import FileLock

        key = hashlib.sha256(repr((args, sorted(kwargs.items()))).encode()).hexdigest()[:20]
        path = self._folder / f"cube-{key}.pt"
        with FileLock(f"{path}.lock"):
            if not path.exists():
                made = self._module.make_cube(*args, **kwargs)
                torch.save(made, path.with_suffix(".tmp"))
                os.replace(path.with_suffix(".tmp"), path)
        return torch.load(path, weights_only=False)


@pytest.fixture(scope="session")
def synthetic(tmp_path_factory, worker_id):
    base = tmp_path_factory.getbasetemp()
    folder = (base.parent if worker_id != "master" else base) / "synthetic-cubes"
    folder.mkdir(exist_ok=True)
    return _RenderedOnce(load_synthetic(), folder)


@pytest.fixture(scope="session")
def small_cube(synthetic):
    """24×24, Fitzpatrick IV skin (exterior arm) with smooth variation, freckles, a scar and a vein."""
    return synthetic.make_cube(24, seed=0, preset="IV exterior", noise=0.25, blur="pyramid")


@pytest.fixture(scope="session")
def small_fit(small_cube):
    from skinlayers.reconstruct.mapfit.fit import fit_cube
    from skinlayers.reconstruct.settings import FitSettings

    return fit_cube(small_cube.cube, FitSettings(**SMALL_FIT))


@pytest.fixture(scope="session")
def small_fit_settings() -> dict:
    """The settings ``small_fit`` ran with (``SMALL_FIT``)."""
    return dict(SMALL_FIT)
