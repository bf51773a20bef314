"""What the fit chooses from the cube: each map's grid (its information) and the forward model (the renderer or each pixel's homogeneous model)."""
