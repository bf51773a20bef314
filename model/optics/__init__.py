"""Skin's optics at a wavelength: the chromophores' spectra, the parameters and their absorption, the optical constants, Fresnel and the radiometry at the surface, the specular lobe, and colour."""
