"""Knuth et al. 2014, Fig. 3 (glossiness row from one filter pyramid; Eq. 3 lookup): the script behind this result.

    python experiments/fig3.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment fig3 ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.fig3`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "fig3", *sys.argv[1:]]))
