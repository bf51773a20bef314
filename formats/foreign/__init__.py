"""Files that other cameras and tools write, read into skinlayers' own types (``cubes``: ENVI, TIFF, NumPy and
HDF5 reflectance cubes)."""
