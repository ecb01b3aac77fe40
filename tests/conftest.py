"""Test-session settings: figures are written, never shown (a non-interactive matplotlib backend chosen
through the environment, as the library itself never switches backends); progress lines silenced unless a
test asks for them."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("IBL_REF_PROGRESS", "0")
