"""Manson & Sloan 2016, Fig. 1 (L1 0.42 of filtered importance sampling with 32 samples against the exact GGX MIP
levels), under four normalisations: the script behind this result.

    python experiments/manson_sloan.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment manson-sloan ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.manson_sloan`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "manson-sloan", *sys.argv[1:]]))
