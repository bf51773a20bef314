"""Acquisition: filter wheel and camera drivers, their simulated twins, and the capture session.

Built by the acquisition issue; this package is the place it lands.
"""
