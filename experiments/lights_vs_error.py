"""Knuth et al. 2014, Sec. 1 and 3 (point lights alone fail for glossy surfaces; PEMs do not): the script behind this result.

    python experiments/lights_vs_error.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment lights-vs-error ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.lights_vs_error`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "lights-vs-error", *sys.argv[1:]]))
