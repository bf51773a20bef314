"""The heterogeneous renderer (DWRR08 §4–5): lights, the gather of each layer's Gaussians over the maps, the blur, tiles and the thin geometry, and the memory a render asks for."""
