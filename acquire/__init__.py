"""Acquisition: filter wheel and camera drivers, their simulated twins, and the capture session.

Real devices: ``FW102C`` (Thorlabs filter wheel over a serial port), ``GPhotoCamera`` (gphoto2).
Simulated: ``VirtualFW102C`` (the wheel's protocol on a pseudo-terminal), ``SimulatedWheel``,
``SimulatedCamera`` photographing a ``SimulatedBench`` (a synthetic ``SkinScene`` rendered with the
model). ``open_devices(rig, simulated=…)`` opens the instruments a rig names; the session
(``run_session``) knows only the ``FilterWheel`` and ``Camera`` base classes. What a session writes
(the manifest, the rig it records) is defined in ``formats/``.
"""

from .connect import Devices, open_devices
from .hardware.devices import Camera, CameraError, DeviceError, ExposureSettings, FilterWheel, WheelError
from .hardware.dng import write_dng
from .hardware.fw102c import FW102C
from .hardware.gphoto import RAW_SUFFIXES, GPhotoCamera, detect_cameras, format_shutter_s, parse_aperture_f, parse_shutter_s
from .hardware.rig import RigConfig, RigError, load_rig
from .simulator.scene import SceneConfig, SceneError, SkinScene, load_scene
from .session import AutoOperator, SessionError, SessionSummary, plan_session, run_session
from .hardware.simdevices import SimulatedCamera, SimulatedWheel
from .simulator.simulated import SimulatedBench, SimulatedFrame
from .simulator.simulation_settings import SimulationError, SimulationSettings, load_simulation_settings
from .hardware.virtual_fw102c import WHEEL_FAULTS, VirtualFW102C

__all__ = [
    "FW102C", "RAW_SUFFIXES", "WHEEL_FAULTS", "AutoOperator", "Camera", "CameraError", "DeviceError", "Devices", "ExposureSettings",
    "FilterWheel", "GPhotoCamera", "RigConfig", "RigError", "SceneConfig", "SceneError", "SessionError", "SessionSummary",
    "SimulatedBench", "SimulatedCamera", "SimulatedFrame", "SimulatedWheel", "SimulationError", "SimulationSettings", "SkinScene",
    "VirtualFW102C", "WheelError", "detect_cameras", "format_shutter_s", "load_rig", "load_scene", "load_simulation_settings",
    "open_devices", "parse_aperture_f", "parse_shutter_s", "plan_session", "run_session", "write_dng",
]
