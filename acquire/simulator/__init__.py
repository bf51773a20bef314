"""The simulated bench: a synthetic patch of skin (scene), its truth rendered at higher fidelity than any fit, and the camera's optics and sensor that photograph it."""
