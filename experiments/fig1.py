"""Knuth et al. 2014, Fig. 1 (materials from diffuse to mirror, our method, Eq. 5): the script behind this result.

    python experiments/fig1.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment fig1 ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.fig1`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "fig1", *sys.argv[1:]]))
