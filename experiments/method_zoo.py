"""Karis 2013 (split sum), Krivanek & Colbert 2008 (FIS), Ramamoorthi & Hanrahan 2001 (SH9), the paper's PEMs + VSM for GGX and cmft against the exact reference, with a budget per method: the script behind this result.

    python experiments/method_zoo.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment method-zoo ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.method_zoo`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "method-zoo", *sys.argv[1:]]))
