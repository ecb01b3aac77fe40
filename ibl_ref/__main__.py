"""``python -m ibl_ref`` is the same as the ``ibl-ref`` command."""

from .cli import main

if __name__ == "__main__":
    raise SystemExit(main())
