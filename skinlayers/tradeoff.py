"""``skinlayers.tradeoff``, the path the docs named before the analyses had a room: the module is
``skinlayers.analyses.tradeoff``; this name keeps working."""

from .analyses.tradeoff import *  # noqa: F403
from .analyses.tradeoff import __all__  # noqa: F401
