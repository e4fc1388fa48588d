"""Shared fixtures: where the real test material (``shared/data``) lives.

Real imagery and logs recorded by others are not part of the repository. Tests that need them
look in ``$PHOTOMAP_DATA`` when set, else in ``../shared/data`` beside the checkout (where CI has
it), and skip with the reason when it is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

DATA_DIR = Path(os.environ.get("PHOTOMAP_DATA")
                or Path(__file__).resolve().parents[1].parent / "shared" / "data")


def shared_data(name: str) -> Path:
    """``shared/data/<name>``, or skip the test with a clear reason."""
    path = DATA_DIR / name
    if not path.exists():
        pytest.skip(f"real test material {name!r} not found in {DATA_DIR} "
                    f"(set PHOTOMAP_DATA to the shared/data folder)")
    return path
