"""The map fit: the fit's steps (fit.py), the homogeneous detour, the last step's σ and flags, and the optimisers that take a level's step."""
