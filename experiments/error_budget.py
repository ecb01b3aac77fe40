"""Error budget of the paper's method (Knuth et al. 2014, Eq. 4-5, Sec. 3.1-3.4): the script behind this result.

    python experiments/error_budget.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment error-budget ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.error_budget`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "error-budget", *sys.argv[1:]]))
