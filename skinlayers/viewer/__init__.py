"""skinlayers in napari: a reader for maps, cubes and sessions (``layers``) and a dock widget that shows,
at the pixel under the cursor, the measured and fitted spectra and the maps with their σ (``inspector``).
The plugin's manifest is ``napari.yaml``; napari and Qt come with the ``viewer`` extra."""
