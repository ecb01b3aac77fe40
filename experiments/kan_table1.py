"""Kan et al. 2015, Table 1 (time to prefilter 8 Phong exponents at once vs map resolution): the script behind this result.

    python experiments/kan_table1.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment kan-table1 ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.kan_table1`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "kan-table1", *sys.argv[1:]]))
