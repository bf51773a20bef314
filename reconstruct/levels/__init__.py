"""What a level of the fit poses: its problem (data, light, renderer), the unknowns and their maps on node grids, the least-squares and Schur-complement algebra."""
