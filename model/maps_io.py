"""``skinlayers.model.maps_io``, the path the docs named before the model had rooms: the module is
``skinlayers.model.patch.maps_io``; this name keeps working."""

from .patch.maps_io import *  # noqa: F403
from .patch.maps_io import __all__  # noqa: F401
