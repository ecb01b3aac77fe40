"""ibl_ref — reference implementation and validation lab for image-based lighting of glossy surfaces.

Core paper: Knuth, Altenhofen, Kuijper, Bender (2014), *Efficient Self-Shadowing Using Image-Based
Lighting on Glossy Surfaces*.  The package layout follows the data flow:

* :mod:`ibl_ref.environment` — environment maps: conventions (:mod:`ibl_ref.environment.envmap`, the single
  source of truth for face order, orientation, texel addressing and units), sampling, resampling, EXR/.hdr files;
* :mod:`ibl_ref.groundtruth` — the exact answer: Phong-lobe convolution (Eq. 4) with error bounds, Kán et al. maps;
* :mod:`ibl_ref.knuth2014` — the paper's approximation: filters, pyramid, glossiness lookup, median cut, PEMs;
* :mod:`ibl_ref.rendering` — cameras, rasteriser, ray casting, VSMs, Eq. 5 shading, the reference renderer;
* :mod:`ibl_ref.lobes` — BRDFs, Kautz & McCool (2000), Meunier et al. (2009);
* :mod:`ibl_ref.synthetic` — synthetic environments and meshes with known answers;
* :mod:`ibl_ref.experiments` — the figure experiments; :mod:`ibl_ref.cli` — the ``ibl-ref`` command.

The short module names of earlier versions (``ibl_ref.convolve``, ``ibl_ref.pyramid``, ``ibl_ref.render``, …)
stay importable: they are the same module objects as their new homes (table ``MOVED`` below).
Importing ``ibl_ref`` itself loads nothing else.
"""

import importlib
import importlib.abc
import importlib.util
import sys

__version__ = "0.1.0"

#: short (pre-layout) module name -> its home in the sub-package layout
MOVED = {
    'ao_modes': 'rendering.ao_modes',
    'brdfs': 'lobes.brdfs',
    'camera': 'rendering.camera',
    'convolution_args': 'groundtruth.convolution_args',
    'convolve': 'groundtruth.convolve',
    'envmap': 'environment.envmap',
    'exr_io': 'environment.exr_io',
    'filters': 'knuth2014.filters',
    'gloss_lookup': 'knuth2014.gloss_lookup',
    'hdr_io': 'environment.hdr_io',
    'image_io': 'rendering.image_io',
    'image_metrics': 'rendering.image_metrics',
    'kan2015': 'groundtruth.kan2015',
    'kautz_mccool2000': 'lobes.kautz_mccool2000',
    'km00_reference': 'lobes.km00_reference',
    'lobe_analysis': 'knuth2014.lobe_analysis',
    'lobe_chain': 'knuth2014.lobe_chain',
    'lobe_render': 'lobes.lobe_render',
    'median_cut': 'knuth2014.median_cut',
    'memory_model': 'knuth2014.memory_model',
    'meunier2009': 'lobes.meunier2009',
    'mitsuba_render': 'rendering.mitsuba_render',
    'moment_convolution': 'groundtruth.moment_convolution',
    'pem': 'knuth2014.pem',
    'phong_convolution': 'groundtruth.phong_convolution',
    'prefiltered_lobes': 'lobes.prefiltered_lobes',
    'probe_files': 'environment.probe_files',
    'profile_convolution': 'lobes.profile_convolution',
    'pyramid': 'knuth2014.pyramid',
    'radiance_policy': 'environment.radiance_policy',
    'raster': 'rendering.raster',
    'raycast': 'rendering.raycast',
    'reference_render': 'rendering.reference_render',
    'render': 'rendering.render',
    'resample': 'environment.resample',
    'sampling': 'environment.sampling',
    'scenes': 'rendering.scenes',
    'seam_metric': 'knuth2014.seam_metric',
    'sh_basis': 'groundtruth.sh_basis',
    'sh_bounds': 'groundtruth.sh_bounds',
    'sh_convolution': 'groundtruth.sh_convolution',
    'sparse_pem': 'knuth2014.sparse_pem',
    'sphere_render': 'rendering.sphere_render',
    'synthetic_envs': 'synthetic.synthetic_envs',
    'synthetic_meshes': 'synthetic.synthetic_meshes',
    'tonemap': 'rendering.tonemap',
    'vsm': 'rendering.vsm',
}


class _MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Makes ``import ibl_ref.<short>`` return the module ``ibl_ref.<MOVED[short]>`` (the same object)."""

    def find_spec(self, fullname, path=None, target=None):
        head, _, short = fullname.partition(".")
        if head == __name__ and short in MOVED:
            return importlib.util.spec_from_loader(fullname, self)
        return None

    def create_module(self, spec):
        return importlib.import_module(f"{__name__}.{MOVED[spec.name.partition('.')[2]]}")

    def exec_module(self, module):
        pass


if not any(isinstance(f, _MovedModuleFinder) for f in sys.meta_path):
    sys.meta_path.insert(0, _MovedModuleFinder())


def __getattr__(name):
    if name in MOVED:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
