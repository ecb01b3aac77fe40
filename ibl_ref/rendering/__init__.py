"""Rendering: cameras, rasteriser, ray casting, variance shadow maps, Eq. 5 shading, the ray-traced reference, the Fig. 6 comparison modes, tone mapping, image metrics and image files."""
