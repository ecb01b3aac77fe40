"""Knuth et al. 2014, Fig. 6 (no occlusion / AO / AO with colour / our method) plus a ray-traced reference: the script behind this result.

    python experiments/fig6.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment fig6 ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.fig6`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "fig6", *sys.argv[1:]]))
