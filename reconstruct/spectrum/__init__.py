"""The point-spectrum fit (fit-spectrum): models with free constants, spectra read from files."""
