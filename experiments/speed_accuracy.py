"""Knuth et al. 2014, Eq. 4 (exact Phong convolution) and Kan et al. 2015 (fast prefiltering): speed vs accuracy: the script behind this result.

    python experiments/speed_accuracy.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment speed-accuracy ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.speed_accuracy`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "speed-accuracy", *sys.argv[1:]]))
