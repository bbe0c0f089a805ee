"""Reflecting surfaces: Fresnel interfaces, heliostat mirrors and rough ground."""
