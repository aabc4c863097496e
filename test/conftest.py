"""Shared fixtures. Real data comes from ../shared/data (read-only, never copied here)."""

from pathlib import Path

from cgags_ros.datasets.synthetic import shared_data_dir
import pytest


@pytest.fixture(scope='session')
def data_dir() -> Path:
    path = shared_data_dir()
    if not (path / 'README.md').exists():
        pytest.fail(f'shared test data not found at {path}; set CGAGS_DATA_DIR')
    return path
