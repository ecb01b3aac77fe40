"""Meunier et al. 2009, Eq. 20-21 (lobe integral), Sec. 4.1-4.2 (tables, product fit: mean error 7.1e-4), Eq. 32-34 (cap fit): the script behind this result.

    python experiments/cosine_lobes.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment cosine-lobes ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.cosine_lobes`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "cosine-lobes", *sys.argv[1:]]))
