"""Knuth et al. 2014, Fig. 7 (frame time vs number of lights, teapot and cloth): the script behind this result.

    python experiments/fig7.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment fig7 ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.fig7`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "fig7", *sys.argv[1:]]))
