"""What the fit says of its maps: the cube's checks and flags, σ and its widening, hairs, grey absorbers."""
