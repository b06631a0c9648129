"""stages.prep: the package's names load lazily from the step modules; run takes the steps in order."""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys
import types
from pathlib import Path

from stages import prep

ROOT = Path(__file__).resolve().parents[2]


def test_the_public_names_load_from_their_step_modules():
    where = {"run": "stage", "decode_image": "decode", "flatten_lighting": "lighting",
             "normalise_contrast": "contrast", "paper_statistics": "band", "narrow_band": "band",
             "stroke_width": "width", "soft_edges": "width", "supersample_factor": "supersampling",
             "supersample": "supersampling", "downsample_factor": "downsampling", "downsample": "downsampling"}
    for name, module in where.items():
        assert getattr(prep, name) is getattr(importlib.import_module(f"stages.prep.{module}"), name)
        assert name in dir(prep)
    # Once every step module is imported (each becomes an attribute of the package), no module's name
    # hides a public function's.
    for info in pkgutil.iter_modules(prep.__path__):
        importlib.import_module(f"stages.prep.{info.name}")
    from stages.prep import downsample, supersample

    assert isinstance(supersample, types.FunctionType) and isinstance(downsample, types.FunctionType)
    assert all(isinstance(getattr(prep, name), types.FunctionType) for name in where)


def test_the_package_alone_imports_no_step():
    """A fully cached run uses the package's own helpers (to_source, piece_windows, ...): no scipy."""
    code = ("import sys, stages.prep as p; p.to_source([[1.0, 2.0]], {'scale': 2}); p.piece_windows({}, (4, 4)); "
            "print(sorted(m for m in sys.modules if m.startswith(('stages.prep.', 'scipy', 'skimage', 'PIL'))))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60,
                         check=False)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
