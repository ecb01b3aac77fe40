"""Knuth et al. 2014, Sec. 3.2 and Sec. 5 (the statements about Figs. 4 and 5, and energy conservation): the script behind this result.

    python experiments/claims.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment claims ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.claims`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "claims", *sys.argv[1:]]))
