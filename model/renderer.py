"""``skinlayers.model.renderer``, the path the docs named before the model had rooms: the module is
``skinlayers.model.render.renderer``; this name keeps working."""

from .render.renderer import *  # noqa: F403
from .render.renderer import __all__  # noqa: F401
from .render.renderer import SkinRenderer  # noqa: F401
