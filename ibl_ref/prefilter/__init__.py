"""Prefilters of the environment for fast image-based lighting, one module per paper (GGX split sum, importance and
filtered importance sampling, SH9 irradiance, GGX lobes mapped to Phong exponents)."""
