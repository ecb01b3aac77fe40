"""Knuth et al. 2014, Eq. 5 and Sec. 4 (renderer accuracy vs lights and VSM resolution against a ray-traced reference): the script behind this result.

    python experiments/render_error.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment render-error ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.render_error`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "render-error", *sys.argv[1:]]))
