"""Kautz & McCool 2000, Figs. 9-18 analogue (Ward teapot: per-pixel exact vs fitted lobes), Sec. 3 and 5: the script behind this result.

    python experiments/km00_render.py [--quick] [--out results] [--PARAM VALUE ...]

is ``ibl-ref experiment km00-render ...`` (``--help`` lists the parameters, outputs and run time).  The experiment
itself — parameters, compute step writing CSV/JSON, plot step reading only those — is
:mod:`ibl_ref.experiments.km00_render`, so it also runs from an installed package.
"""

import sys

from ibl_ref.cli import main

if __name__ == "__main__":
    sys.exit(main(["experiment", "km00-render", *sys.argv[1:]]))
