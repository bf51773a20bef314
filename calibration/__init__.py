"""Calibration: raw frames of a session to a reflectance cube (dark, flat, gray card, polarization,
window detection and band alignment). Built by the calibration issue; this package is where it lands.
"""
