"""``skinlayers.model.layer_shapes``, the path the docs named before the model had rooms: the module is
``skinlayers.model.column.layer_shapes``; this name keeps working."""

from .column.layer_shapes import *  # noqa: F403
from .column.layer_shapes import __all__  # noqa: F401
from .column.layer_shapes import main

if __name__ == "__main__":
    main()
