"""Kautz & McCool 2000, Fig. 7 (RMS error of the greedy lobe fit vs number of lobes), Sec. 4-5: the script behind this result.

    python experiments/km00.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment km00 ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.km00`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "km00", *sys.argv[1:]]))
