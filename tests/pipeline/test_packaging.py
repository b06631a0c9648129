"""The shipped model files travel with a (non-editable) install."""

from __future__ import annotations

import fnmatch
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_package_data_covers_the_shipped_weights():
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["*"]
    shipped = sorted(p.name for p in (ROOT / "stages" / "keypoints" / "weights").iterdir() if p.is_file())
    assert {"keypoints.pt", "keypoints_procedural.pt", "type_classifier.npz"} <= set(shipped)
    missing = [n for n in shipped if not any(fnmatch.fnmatch(n, pat) for pat in patterns)]
    assert missing == [], f"not in [tool.setuptools.package-data]: {missing}"


# Import name → distribution name, for the runtime dependencies whose names differ.
_DIST_OF = {"PIL": "pillow", "skimage": "scikit-image", "hydra": "hydra-core", "yaml": "pyyaml",
            "distributed": "dask", "sklearn": "scikit-learn", "pillow_heif": "pillow-heif"}


def _declared(extras: bool = False) -> dict[str, str]:
    """The runtime dependencies, or (``extras``) those of the optional extras users install (not `test`)."""
    import re

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    deps = ([d for name, ds in project["optional-dependencies"].items() if name != "test" for d in ds]
            if extras else project["dependencies"])
    return {re.match(r"[A-Za-z0-9_.\-]+", d).group(0).lower(): d for d in deps}


def _imported_modules() -> set[str]:
    """Top-level modules that the installed code (pipeline/, stages/, conf/) imports."""
    import ast
    import sys

    names: set[str] = set()
    for folder in ("pipeline", "stages", "conf"):
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    names |= {a.name.split(".")[0] for a in node.names}
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names.add(node.module.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names and n not in ("pipeline", "stages", "conf")}


def test_runtime_dependencies_are_what_the_code_imports():
    """Every third-party import is declared (a dependency, or an optional extra's: pillow-heif), and every
    declared one is imported."""
    declared, optional = _declared(), _declared(extras=True)
    used = {_DIST_OF.get(m, m).lower() for m in _imported_modules()}
    assert sorted(used - set(declared) - set(optional)) == [], "imported but not declared in pyproject.toml"
    assert sorted((set(declared) | set(optional)) - used) == [], "declared in pyproject.toml but never imported"


def test_pulp_lower_bound_has_add_variable():
    """stages/select/stage.py builds its problem with LpProblem.add_variable, new in PuLP 3.3.1 (its HISTORY)."""
    import re

    import pulp

    lower = re.search(r">=\s*([\d.]+)", _declared()["pulp"]).group(1)
    assert tuple(int(x) for x in lower.split(".")) >= (3, 3, 1)
    assert hasattr(pulp.LpProblem, "add_variable")


def test_project_metadata_has_no_deprecation_warning():
    """`project.license` is an SPDX string (a TOML table is deprecated by setuptools)."""
    import warnings

    import pytest

    config = pytest.importorskip("setuptools.config.pyprojecttoml")
    from setuptools.dist import Distribution

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        config.apply_configuration(Distribution(), str(ROOT / "pyproject.toml"))
    assert [str(w.message).splitlines()[0] for w in caught] == []


def test_docs_say_what_the_code_does():
    """Statements issue 18 found false: the heads' activation, the CG solver, 5 of 6 as 75 %, stages reading files."""
    import inspect

    import stages
    from stages.field import stage as field
    from stages.keypoints import network
    from stages.prep import stage as prep

    assert "sigmoid)" not in inspect.getdoc(network.KeypointNet) and "torch.sigmoid" not in inspect.getsource(network)
    assert "(scipy) with a Jacobi" not in field.__doc__ and "_conjugate_gradient" in field.__doc__
    assert "same 75 % share" not in prep.__doc__
    assert "never read files" not in stages.__doc__


def test_the_readme_configuration_examples_compose(compose_cfg):
    """Every override the README's "Configuration groups" table shows is a key of the config."""
    import re

    text = (ROOT / "README.md").read_text()
    table = text[text.index("## Configuration groups"):text.index("\n## ", text.index("## Configuration groups") + 1)]
    examples = [o for cell in re.findall(r"`([^`]*=[^`]*)`", table) for o in cell.split()]
    assert "export.corners.enabled=false" in examples and len(examples) >= 10
    for override in examples:
        compose_cfg(override)             # an unknown key fails here, as it would on the command line
