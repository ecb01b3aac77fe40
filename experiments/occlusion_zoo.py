"""The occlusion engines ship (AO, multi-bounce AO, specular occlusion, horizon, GTSO cones, PRT, per-region visibility) with oracle and screen-space inputs against exact visibility: the script behind this result.

    python experiments/occlusion_zoo.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment occlusion-zoo ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.occlusion_zoo`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "occlusion-zoo", *sys.argv[1:]]))
