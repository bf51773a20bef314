"""Opening a rig's instruments: real, simulated, or a simulated camera on a real wheel — chosen in one place.

``open_devices(rig, simulated=…)`` is what the capture command and the demo both call. It returns a
``Devices`` record (a context manager: the camera and the wheel are closed on leaving it, also on an
error or Ctrl-C):

| ``simulated`` | ``rig.camera.driver`` | wheel | camera |
|---|---|---|---|
| True | any | ``SimulatedWheel`` | ``SimulatedCamera`` photographing a ``SimulatedBench`` |
| False | ``simulated`` | ``FW102C`` on ``rig.wheel.port`` (a real wheel, or the pty twin) | ``SimulatedCamera`` |
| False | ``gphoto2`` | ``FW102C`` on ``rig.wheel.port`` | ``GPhotoCamera`` |

With a simulated camera, ``Devices.rig`` is the rig as the bench uses it (the gray card's region where the
bench puts it), and ``Devices.notes`` what the session's manifest records of the simulation.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Optional

from ..formats.errors import InputError
from ..formats.rig import RigConfig
from .hardware.devices import Camera, FilterWheel

if TYPE_CHECKING:
    from .simulator.simulated import SimulatedBench

__all__ = ["Devices", "open_devices"]


@dataclass
class Devices:
    """A rig's opened instruments; ``bench`` is the simulated bench when the camera is simulated."""

    rig: RigConfig
    wheel: FilterWheel
    camera: Camera
    bench: Optional["SimulatedBench"] = None
    notes: dict = field(default_factory=dict)

    @property
    def simulated(self) -> bool:
        """True when the camera photographs a simulated bench."""
        return self.bench is not None

    def place(self, target: str) -> None:
        """What the operator places ("spectralon", "skin") is placed on the simulated bench too."""
        if self.bench is not None:
            self.bench.set_target(target)

    def close(self) -> None:
        """Close the camera, then the wheel (each once; a failing close does not keep the other open)."""
        try:
            self.camera.close()
        finally:
            self.wheel.close()

    def __enter__(self) -> "Devices":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_devices(
    rig: RigConfig,
    *,
    simulated: bool = False,
    scene: str | Path | None = None,
    simulation: str | Path | None = None,
    seed: int = 0,
    wheel_time_scale: float = 1.0,
    wheel_port: str | None = None,
    device: str | None = None,
    truth: dict | None = None,
) -> Devices:
    """Open the instruments of ``rig`` (see the module docstring for which ones).

    ``scene`` and ``simulation``: YAML files of the simulated skin and bench (None: the embedded
    ``configs/scene.yaml`` and ``configs/simulation.yaml``); ``seed``: of the simulated scene, noise,
    flash and motion; ``wheel_time_scale``: the simulated wheel's move times (0: instant); ``device``:
    where the simulator renders (None: CUDA when there is one). A wheel that is not simulated is opened
    on ``wheel_port``, else on ``rig.wheel.port`` (a resumed session keeps its recorded rig, whatever
    port the wheel is on today). ``truth``: overrides of the simulation's ``truth`` settings (its physics,
    photons)."""
    bench = None
    notes: dict = {}
    if simulated or rig.camera.driver == "simulated":
        from .simulator.scene import load_scene  # noqa: PLC0415 (the simulator loads the model and its tables)
        from .simulator.simulated import SimulatedBench  # noqa: PLC0415
        from .simulator.simulation_settings import load_simulation_settings  # noqa: PLC0415

        settings = load_simulation_settings(simulation, **({"truth": truth} if truth else {}))
        bench = SimulatedBench(rig, load_scene(scene), settings, seed, device=device)
        rig = bench.rig_as_used()
        notes = {"seed": seed, "scene": str(scene or "configs/scene.yaml (embedded)"),
                 "simulation": str(simulation or "configs/simulation.yaml (embedded)"), "truth_physics": settings.truth.physics}
        if settings.truth.physics == "transport":
            notes["truth_photons_per_node"] = settings.truth.photons
    wheel = _wheel(rig, simulated, wheel_time_scale, wheel_port or rig.wheel.port)
    try:
        camera = _camera(rig, bench, wheel)
    except BaseException:
        wheel.close()
        raise
    return Devices(rig, wheel, camera, bench, notes)


def _wheel(rig: RigConfig, simulated: bool, time_scale: float, port: str | None) -> FilterWheel:
    if simulated:
        from .hardware.simdevices import SimulatedTunableFilter, SimulatedWheel  # noqa: PLC0415

        kind = SimulatedWheel if rig.wheel.position_count in SimulatedWheel.POSITION_COUNTS else SimulatedTunableFilter
        return kind(rig.wheel.position_count, time_scale=time_scale)
    if not port:
        raise InputError("no filter wheel port: set wheel.port in the rig file or pass --wheel-port")
    from .hardware.fw102c import FW102C  # noqa: PLC0415

    return FW102C.open(port, rig.wheel)


def _camera(rig: RigConfig, bench: Optional["SimulatedBench"], wheel: FilterWheel) -> Camera:
    if bench is not None:
        from .hardware.simdevices import SimulatedCamera  # noqa: PLC0415

        return SimulatedCamera(bench, wheel)
    from .hardware.gphoto import GPhotoCamera  # noqa: PLC0415

    return GPhotoCamera(rig.camera)
