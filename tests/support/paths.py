"""Where the repository is, for tests that read its files or run its commands from its root, wherever they sit
under tests/."""

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]  # tests/support/paths.py -> the repository
