"""The engines' roughness → MIP-level mappings (glTF-IBL-Sampler, Filament, Unity, Unreal Engine 4, three.js) at
equal memory, in their own chains and mismatched, against the exact GGX prefilter: the script behind this result.

    python experiments/mip_mappings.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment mip-mappings ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON/Markdown, plot step reading only the CSV — is
:mod:`ibl_ref.experiments.mip_mappings`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "mip-mappings", *sys.argv[1:]]))
