"""``skinlayers.model.layer_totals``, the path the docs named before the model had rooms: the module is
``skinlayers.model.column.layer_totals``; this name keeps working."""

from .column.layer_totals import *  # noqa: F403
from .column.layer_totals import __all__  # noqa: F401
from .column.layer_totals import main

if __name__ == "__main__":
    main()
