"""``skinlayers.truths``, the path the docs named before the analyses had a room: the module is
``skinlayers.analyses.truths``; this name keeps working."""

from .analyses.truths import *  # noqa: F403
from .analyses.truths import __all__  # noqa: F401
from .analyses.truths import main

if __name__ == "__main__":
    main()
