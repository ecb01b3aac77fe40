"""Knuth et al. 2014, Fig. 4 (s = 1 lobe of each 5x5 filter's MIP pyramid vs the cosine target): the script behind this result.

    python experiments/fig4.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment fig4 ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.fig4`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "fig4", *sys.argv[1:]]))
