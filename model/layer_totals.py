"""``skinlayers.model.layer_totals``, the path the docs named before the model had rooms: the module is
``skinlayers.model.column.layer_totals`` (its builder ``skinlayers.model.column.adding_doubling``); this name keeps
working, ``python -m`` included (it regenerates the tables)."""

from .column.adding_doubling import main
from .column.layer_totals import *  # noqa: F403
from .column.layer_totals import __all__  # noqa: F401

if __name__ == "__main__":
    main()
