"""What the fit writes: maps.exr, fit.json, report.png and their statistics."""
