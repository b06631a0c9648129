"""``polyvec-train``: the command front-end of the keypoint training (:mod:`stages.keypoints.training`).

Usage::

    polyvec-train                                   # conf/train_app.yaml: train + keypoints + prep
    polyvec-train train.steps=2000 train.out_dir=runs/small train.network.level_channels=[8,16,32,64]
    python -m pipeline.train --plain conf_dir [key=value…]            # the same without Hydra
    python -m pipeline.train --class-branch conf_dir train.init_weights=… [key=value…]
    python -m pipeline.train --type-classifier conf_dir [key=value…]

``--plain`` composes the ``train``, ``keypoints`` and ``prep`` sections from the YAML files alone, so
training also runs where Hydra is not installed; ``--class-branch`` re-trains only the class branch on
a frozen detector; ``--type-classifier`` trains the typing perceptron of :mod:`stages.keypoints.valence`.
"""

from __future__ import annotations

import sys
from pathlib import Path

from stages.keypoints.training import train, train_class_branch, train_type_classifier

# ------------------------------------------------------------------------------------------------
# Entry points


def _set(d: dict, dotted: str, value) -> None:
    keys = dotted.split(".")
    for k in keys[:-1]:
        d = d[k]
    d[keys[-1]] = value


def compose_plain(conf_dir: str | Path, overrides: list[str]) -> dict:
    """Compose train_app's sections from YAML without Hydra (for machines that lack it).

    Each section is checked against its dataclass, as Hydra does with the structured configs: a
    missing, unknown or ill-typed key is an error here, before any training starts.
    """
    import yaml

    from stages.config import from_section
    from stages.keypoints import KeypointsConfig
    from stages.keypoints.training.config import TrainConfig
    from stages.prep import PrepConfig

    conf_dir = Path(conf_dir)
    schemas = {"train": TrainConfig, "keypoints": KeypointsConfig, "prep": PrepConfig}
    cfg = {name: yaml.safe_load((conf_dir / name / "default.yaml").read_text()) for name in schemas}
    for o in overrides:
        k, v = o.split("=", 1)
        _set(cfg, k, yaml.safe_load(v))
    for name, cls in schemas.items():
        from_section(cls, cfg[name], name)
    return cfg


def main() -> None:
    """``polyvec-train``; a bad config key or value is one ``polyvec-train: error:`` line and exit 2."""
    from stages.errors import InputError

    try:
        _main()
    except InputError as exc:
        print(f"polyvec-train: error: {exc}", file=sys.stderr)
        sys.exit(2)


def _main() -> None:
    """``polyvec-train`` (Hydra). ``--plain CONF_DIR key=value…`` composes without Hydra."""
    if len(sys.argv) > 2 and sys.argv[1] == "--plain":
        train(compose_plain(sys.argv[2], sys.argv[3:]))
        return
    if len(sys.argv) > 2 and sys.argv[1] == "--class-branch":
        train_class_branch(compose_plain(sys.argv[2], sys.argv[3:]))
        return
    if len(sys.argv) > 2 and sys.argv[1] == "--type-classifier":
        train_type_classifier(compose_plain(sys.argv[2], sys.argv[3:]))
        return
    import hydra
    from omegaconf import OmegaConf

    from pipeline.hydra_command import no_stray_multirun

    @hydra.main(version_base=None, config_path="pkg://conf", config_name="train_app")
    def _app(cfg) -> None:
        train(OmegaConf.to_container(cfg, resolve=True))

    with no_stray_multirun():
        _app()


if __name__ == "__main__":
    main()
