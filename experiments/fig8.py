"""Knuth et al. 2014, Fig. 8 (memory of PEMs and VSMs) and Sec. 6 (sparse PEMs, not built in the paper): the script behind this result.

    python experiments/fig8.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment fig8 ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.fig8`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "fig8", *sys.argv[1:]]))
