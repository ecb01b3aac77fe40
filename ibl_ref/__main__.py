"""``python -m ibl_ref`` is the same as the ``ibl-ref`` command."""

import sys

try:  # Ctrl-C while the command line module loads: the same one line as later (ibl_ref.cli.interrupts)
    from .cli import main
except KeyboardInterrupt:
    print("ibl-ref: interrupted", file=sys.stderr)
    raise SystemExit(130) from None

if __name__ == "__main__":
    raise SystemExit(main())
