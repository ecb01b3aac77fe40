"""Knuth et al. 2014, Eq. 4 (the exact Phong lobe average the lab uses as ground truth): convergence: the script behind this result.

    python experiments/convergence.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment convergence ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.convergence`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "convergence", *sys.argv[1:]]))
