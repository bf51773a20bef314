"""``skinlayers.batch``, the path the docs named before the analyses had a room: the module is
``skinlayers.studies.batch``; this name keeps working."""

from .studies.batch import *  # noqa: F403
from .studies.batch import WORKER_ENVIRON, __all__  # noqa: F401
