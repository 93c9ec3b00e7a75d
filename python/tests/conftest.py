"""Shared paths for the Python tests (CTest sets HAPTREE_BUILD_DIR / HAPTREE_SOURCE_DIR)."""
import os
import pathlib

import pytest

HERE = pathlib.Path(__file__).resolve().parent
SOURCE_DIR = pathlib.Path(os.environ.get("HAPTREE_SOURCE_DIR", HERE.parent.parent))
BUILD_DIR = pathlib.Path(os.environ.get("HAPTREE_BUILD_DIR", SOURCE_DIR / "build"))


def tool(rel):
    p = BUILD_DIR / rel
    if not p.exists():
        pytest.fail(f"{p} is missing: build it first (cmake --build build)")
    return str(p)
