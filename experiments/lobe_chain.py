"""Knuth et al. 2014, Sec. 3.2 / Eq. 3-4: the filter pyramid's lookup vs the exact Phong lobe average, and the exact-lobe chain (not in the paper): the script behind this result.

    python experiments/lobe_chain.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment lobe-chain ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.lobe_chain`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "lobe-chain", *sys.argv[1:]]))
