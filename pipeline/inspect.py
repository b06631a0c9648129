"""``polyvec-inspect``: look inside the artifact store.

Examples
--------
``polyvec-inspect list``                          images in the store
``polyvec-inspect list drawing.png``              artifacts of one image (stage, key, size, time, config)
``polyvec-inspect show graph 3fa2``               one manifest (key prefixes are enough)
``polyvec-inspect render drawing.png field -o field.png``   an artifact drawn over the drawing
``polyvec-inspect page drawing.png``              the interactive inspection page (drawing.html)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pipeline.engine.lookup import STAGE_ORDER, artifacts_of
from pipeline.engine.registry import STAGES
from pipeline.engine.store import ArtifactStore

def resolve(store: ArtifactStore, stage: str, key_prefix: str | None, image: str | None) -> str:
    """Full key of an artifact: from a key prefix, the newest one of ``image``, or the only image's.

    With neither a key prefix nor an image, the stage's artifact is taken when the store holds
    artifacts of that stage for one image only (the newest of them).
    """
    if key_prefix and image is None and Path(key_prefix).is_file():
        key_prefix, image = None, key_prefix  # `show graph drawing.png`: an image, not a key
    if image is not None and not key_prefix:
        keys = [k for s, k, _ in artifacts_of(store, image) if s == stage]
        if not keys:
            raise LookupError(f"no {stage} artifact for {image} in {store.url}")
        return keys[-1]
    found = [(k, m) for s, k, m in store.iter_manifests() if s == stage and k.startswith(key_prefix or "")]
    if not found:
        raise LookupError(f"no {stage} artifact with key {key_prefix or ''}* in {store.url}")
    if not key_prefix:
        images = {m.get("image") for _, m in found}
        if len(images) > 1:
            raise LookupError(f"the store holds {stage} artifacts of {len(images)} images: give --image IMAGE "
                              "or a key prefix")
        return sorted(found, key=lambda t: t[1].get("written_at", 0))[-1][0]
    if len(found) > 1:
        raise LookupError(f"key prefix {key_prefix} is ambiguous: {', '.join(k[:12] for k, _ in found)}")
    return found[0][0]


def _flatten(cfg, prefix: str = "") -> dict:
    if isinstance(cfg, dict):
        out = {}
        for k, v in cfg.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: cfg}


def config_differences(configs: list[dict]) -> list[dict]:
    """Per config, only the (dotted) settings that differ among ``configs``.

    Parameters
    ----------
    configs : list of dict
        Configs of artifacts of one stage (e.g. the flow artifacts of a λ sweep).

    Returns
    -------
    list of dict
        Same order; empty dicts when all configs are equal (or there is only one).
    """
    flat = [_flatten(c or {}) for c in configs]
    keys = sorted(set().union(*flat)) if flat else []
    differ = [k for k in keys if len({json.dumps(f.get(k), sort_keys=True) for f in flat}) > 1]
    return [{k: f.get(k) for k in differ} for f in flat]


def _short_config(cfg: dict, width: int = 60) -> str:
    text = json.dumps(cfg, sort_keys=True, separators=(",", ":"))
    return text if len(text) <= width else text[: width - 1] + "…"


def cmd_list(store: ArtifactStore, image: str | None, console) -> int:
    from rich.markup import escape
    from rich.table import Table

    if image is None:
        images: dict[str, dict] = {}
        for stage, key, m in store.iter_manifests():
            d = images.setdefault(m.get("image", "?"), {"name": m.get("image_name", "?"), "n": 0, "stages": set()})
            d["n"] += 1
            d["stages"].add(stage)
        table = Table(title=escape(f"store {store.url}: {len(images)} image(s)"))
        for col in ("image key", "name", "artifacts", "stages"):
            table.add_column(col)
        for k, d in sorted(images.items(), key=lambda t: t[1]["name"]):
            stages = ", ".join(sorted(d["stages"], key=lambda s: STAGE_ORDER.get(s, 99)))
            table.add_row(k[:12], escape(str(d["name"])), str(d["n"]), stages)
        console.print(table)
        return 0
    rows = artifacts_of(store, image)
    if not rows:
        console.print(f"nothing stored for {image} in {store.url}", markup=False)
        return 1
    table = Table(title=escape(f"{image}: {len(rows)} artifact(s) in {store.url}"))
    for col in ("stage", "key", "version", "size", "seconds", "peak MB", "config"):
        table.add_column(col)
    # A stage with several artifacts (a sweep) shows what differs between them, not the common prefix.
    by_stage: dict[str, list[int]] = {}
    for n, (stage, _, _) in enumerate(rows):
        by_stage.setdefault(stage, []).append(n)
    shown = {}
    for stage, idx in by_stage.items():
        if len(idx) > 1:
            for n, diff in zip(idx, config_differences([rows[n][2].get("config", {}) for n in idx])):
                shown[n] = diff
    for n, (stage, key, m) in enumerate(rows):
        size = store.size_bytes(stage, key)
        table.add_row(stage, key[:12], str(m.get("version")), f"{size / 1024:.0f} KB",
                      f"{m.get('duration_s', 0):.2f}", str(m.get("peak_rss_mb", "")),
                      escape(_short_config(shown.get(n, m.get("config", {})))))
    console.print(table)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Console entry point."""
    from rich.console import Console

    parser = argparse.ArgumentParser(prog="polyvec-inspect", description="Inspect the polyvec artifact store.")
    parser.add_argument("--store", default="artifacts", help="store path or fsspec URL (default: artifacts)")
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("list", help="images in the store, or the artifacts of one image")
    p.add_argument("image", nargs="?")
    p = sub.add_parser("show", help="print one artifact's manifest and data summary")
    p.add_argument("stage", choices=[s.name for s in STAGES])
    p.add_argument("key", nargs="?", help="key or key prefix (default: the artifact of the store's only image)")
    p.add_argument("--image", help="take the newest artifact of this image")
    p = sub.add_parser("render", help="draw an artifact over its drawing into a PNG")
    p.add_argument("image", help="the input image (its newest artifact is drawn) ")
    p.add_argument("stage", choices=[s.name for s in STAGES])
    p.add_argument("--key", help="key prefix, to pick one of several artifacts")
    p.add_argument("-o", "--out", help="PNG path (default: <image stem>.<stage>.png)")
    p.add_argument("--scale", type=int, default=2)
    p = sub.add_parser("page", help="write the interactive inspection page (HTML) of a drawing")
    p.add_argument("image", help="the input image (its newest chain of artifacts is drawn)")
    p.add_argument("-o", "--out", help="HTML path (default: <image stem>.html)")
    args = parser.parse_args(argv)
    console = Console()
    try:
        store = ArtifactStore(args.store, create=False)  # inspecting never creates a store
    except FileNotFoundError as exc:
        print(f"polyvec-inspect: error: {exc}", file=sys.stderr)
        return 2
    try:
        if args.cmd == "list":
            return cmd_list(store, args.image, console)
        if args.cmd == "show":
            key = resolve(store, args.stage, args.key, args.image)
            manifest = store.manifest(args.stage, key)
            console.print_json(json.dumps(manifest))
            data = store.load(args.stage, key).data
            summary = {k: (f"list[{len(v)}]" if isinstance(v, list) else v) for k, v in data.items()
                       if not isinstance(v, str) or len(v) < 200}
            console.print_json(json.dumps(summary, default=str))
            return 0
        if args.cmd == "page":
            from pipeline.page import write_page

            out = write_page(store, args.image, args.out or f"{Path(args.image).stem}.html")
            console.print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB)", highlight=False, soft_wrap=True,
                          markup=False)
            return 0
        key = resolve(store, args.stage, args.key, args.image)
        from PIL import Image

        from pipeline.render import render_artifact

        rgb = render_artifact(store, args.stage, key, scale=args.scale)
        out = Path(args.out or f"{Path(args.image).stem}.{args.stage}.png")
        Image.fromarray(rgb).save(out)
        console.print(f"wrote {out}", markup=False)
        return 0
    except (LookupError, OSError) as exc:
        print(f"polyvec-inspect: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
