"""The transport reference: Monte Carlo radiative transport through the layered, laterally heterogeneous
skin the renderer models — the truth the diffusion model and the fit are measured against.

- ``walk``: the photon walk (delta tracking, implicit capture, Henyey–Greenstein scattering, Fresnel
  boundaries, the interface absorber at each crossing), vectorised torch on any device;
- ``reference``: skin's maps or one parameter set to reflectance with standard errors
  (``TransportRenderer``), with the renderer's lights and radiometric convention.

It shares no code with the diffusion profiles. Validation: ``tests/model/test_transport_reference.py``
(homogeneous slabs and two layers against adding-doubling) and docs/transport.md.
"""

from .reference import BYTES_PER_PHOTON, TransportRenderer, TransportResult, TransportTotals, check_physics_options
from .walk import Medium, Tally, walk

__all__ = ["BYTES_PER_PHOTON", "Medium", "Tally", "TransportRenderer", "TransportResult", "TransportTotals", "check_physics_options",
           "walk"]
