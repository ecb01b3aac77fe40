"""ibl_ref — reference implementation and validation lab for image-based lighting of glossy surfaces.

Core paper: Knuth, Altenhofen, Kuijper, Bender (2014), *Efficient Self-Shadowing Using Image-Based
Lighting on Glossy Surfaces*.  The package layout follows the data flow:

* :mod:`ibl_ref.environment` — environment maps: conventions (:mod:`ibl_ref.environment.envmap`, the single
  source of truth for face order, orientation, texel addressing and units), sampling, resampling, EXR/.hdr files,
  and the validated environment every stage trusts (:mod:`ibl_ref.environment.validated`);
* :mod:`ibl_ref.groundtruth` — the exact answer: Phong-lobe convolution (Eq. 4) with error bounds, Kán et al. maps;
* :mod:`ibl_ref.knuth2014` — the paper's approximation: filters, pyramid, glossiness lookup, median cut, PEMs;
* :mod:`ibl_ref.rendering` — cameras, rasteriser, ray casting, VSMs, Eq. 5 shading, the reference renderer;
* :mod:`ibl_ref.lobes` — BRDFs, Kautz & McCool (2000), Meunier et al. (2009);
* :mod:`ibl_ref.synthetic` — synthetic environments and meshes with known answers;
* :mod:`ibl_ref.experiments` — the figure experiments; :mod:`ibl_ref.cli` — the ``ibl-ref`` command.

Importing ``ibl_ref`` itself loads nothing else; every name is imported from its one home (the README's table
"Where each concept lives").
"""

__version__ = "0.1.0"
