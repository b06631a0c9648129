"""stages.prep.lighting: the paper's uneven brightness is divided out; even lighting is left exactly alone."""

from __future__ import annotations

import numpy as np

from stages.prep import LightingConfig
from stages.prep.lighting import even_lighting, flatten_lighting


def _page(shadow: float) -> np.ndarray:
    """200×200 white paper with a 3-px dark square outline, darkened by ``shadow`` towards the right."""
    grey = np.ones((200, 200))
    grey[50:150, 50:53] = grey[50:150, 147:150] = 0.1
    grey[50:53, 50:150] = grey[147:150, 50:150] = 0.1
    return grey * (1.0 - shadow * np.linspace(0, 1, 200)[None, :])


def test_even_lighting_is_returned_as_it_is():
    grey = _page(0.0)
    out, variation = flatten_lighting(grey, 41, 0.12)
    assert out is grey and variation < 0.12


def test_a_shadow_is_divided_out_and_the_strokes_stay_ink():
    grey = _page(0.4)
    out, variation = flatten_lighting(grey, 41, 0.12)
    assert variation > 0.3
    paper = np.ones((200, 200), bool)
    paper[45:156, 45:156] = False
    assert grey[paper].min() < 0.65 and out[paper].min() > 0.9    # the shaded paper is white again
    assert out[50:150, 147:150].max() < 0.3                        # a stroke in the shadow is still ink


def test_the_step_says_when_it_divided_the_lighting_out():
    cfg = LightingConfig(enabled=True, window_px=41, min_range=0.12)
    out, notes = even_lighting(_page(0.4), cfg)
    assert len(notes) == 1 and notes[0].startswith("uneven lighting") and "prep.lighting" in notes[0]
    grey = _page(0.0)
    assert even_lighting(grey, cfg) == (grey, [])
    shaded = _page(0.4)
    out, notes = even_lighting(shaded, LightingConfig(enabled=False, window_px=41, min_range=0.12))
    assert out is shaded and notes == []
