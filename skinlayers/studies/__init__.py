"""Many sessions at once: batch reconstruction on Dask and the study that tabulates and charts its maps."""
