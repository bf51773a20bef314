"""``skinlayers.model.thin``, the path the docs named before the model had rooms: the module is
``skinlayers.model.render.thin``; this name keeps working."""

from .render.thin import *  # noqa: F403
from .render.thin import __all__  # noqa: F401
from .render.thin import render_transmission  # noqa: F401
