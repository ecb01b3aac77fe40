"""ibl_ref — reference implementation and validation lab for image-based lighting of glossy surfaces.

Core paper: Knuth, Altenhofen, Kuijper, Bender (2014), *Efficient Self-Shadowing Using Image-Based
Lighting on Glossy Surfaces*.  Conventions (face order, orientation, texel addressing, units) are defined
once, in :mod:`ibl_ref.envmap`.
"""

__version__ = "0.1.0"
