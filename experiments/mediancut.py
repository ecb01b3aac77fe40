"""Knuth et al. 2014, Sec. 3.1 (median cut, Debevec 2008) and Meunier et al. 2009, Eq. 32-34 (equivalent lobes): the script behind this result.

    python experiments/mediancut.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment mediancut ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.mediancut`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "mediancut", *sys.argv[1:]]))
