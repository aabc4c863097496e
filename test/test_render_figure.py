"""
scripts/render_figure.py renders the README's before/after picture from the committed fixture.

Run as users run it (its own process), into a temporary file: the pair must register (the
same bounds as test_fixture_node.py), and the PNG must show both clouds in both panels.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
import subprocess
import sys

import numpy as np
import pytest

pytestmark = pytest.mark.subprocess
REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / 'scripts' / 'render_figure.py'
COMMITTED = REPO / 'docs' / 'images' / 'registration_pair.png'
MAX_RE_DEG, MAX_TE_M = 2.0, 0.2
MAX_BYTES = 300_000
# A fresh clone compiles the numba code first (no numba cache yet).
TIMEOUT_S = 900


def script_module():
    spec = importlib.util.spec_from_file_location('render_figure', SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def coloured_pixels(image: np.ndarray, colour: str) -> np.ndarray:
    """
    Return a mask of the pixels of ``image`` (H, W, 3+) of the hue of ``colour``.

    By hue and saturation, not by value: the points are antialiased and partly
    transparent, so few pixels carry the colour exactly; text and axes (grey) never count.
    """
    from matplotlib.colors import rgb_to_hsv, to_rgb

    hsv = rgb_to_hsv(np.clip(image[..., :3], 0.0, 1.0))
    distance = np.abs(hsv[..., 0] - rgb_to_hsv(np.asarray(to_rgb(colour)))[0])
    return (np.minimum(distance, 1.0 - distance) < 0.04) & (hsv[..., 1] > 0.3)


def test_render_figure_writes_a_registered_pair(tmp_path):
    pytest.importorskip('matplotlib')
    import matplotlib.image

    out = tmp_path / 'figure' / 'pair.png'
    run = subprocess.run([sys.executable, str(SCRIPT), '--output', str(out)], cwd=tmp_path,
                         capture_output=True, text=True, timeout=TIMEOUT_S)
    assert run.returncode == 0, f'{run.stdout}\n{run.stderr}'
    summary = json.loads(run.stdout.strip().splitlines()[-1])
    assert summary['valid'], summary
    assert summary['re_deg'] <= MAX_RE_DEG and summary['te_m'] <= MAX_TE_M, summary
    assert Path(summary['output']) == out

    assert out.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    assert 20_000 < out.stat().st_size < MAX_BYTES, out.stat().st_size
    image = matplotlib.image.imread(out)
    height, width = image.shape[:2]
    assert width > 800 and height > 400, image.shape
    module = script_module()
    # Each half (panel) shows both clouds: many pixels of each colour.
    for half in (image[:, :width // 2], image[:, width // 2:]):
        for colour in (module.SOURCE_COLOUR, module.TARGET_COLOUR):
            assert coloured_pixels(half, colour).sum() > 1000, colour


def test_committed_figure_is_small_png():
    assert COMMITTED.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    assert COMMITTED.stat().st_size < MAX_BYTES
