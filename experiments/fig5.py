"""Knuth et al. 2014, Fig. 5 (relative lobe error vs s_Phong of the five filters, Sec. 5): the script behind this result.

    python experiments/fig5.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment fig5 ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.fig5`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "fig5", *sys.argv[1:]]))
