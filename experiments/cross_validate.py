"""Cross-validation of the converged reference against Mitsuba 3 (3 scenes × 3 materials + a probe with a small sun): the script behind this result.

    python experiments/cross_validate.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment cross-validate ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.cross_validate`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "cross-validate", *sys.argv[1:]]))
