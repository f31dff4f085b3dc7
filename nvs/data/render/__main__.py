"""`python -m nvs.data.render <chairs|cars|drive|contact> [key=value ...]`.

Objects: size=256 out=data/<category>_<size> seed=0 max_models=N supersample=3 pairs_per_model=30
         workers=<cores, at most 2> (models rendered in that many processes; same files)
         assets=DIR: the packages scripts/install_object_assets.sh extracted (default: $NVS_ASSETS, else
         data/assets under the working directory; without it only the installed Debian packages' models)
Drive:   size=256 out=data/drive_<size> seed=0 sequences=10 frames=200 supersample=3
         sources=stk:2,torcs camera=kitti|wide
Contact: out=docs/contact_sheet.png chairs=DIR cars=DIR drive=DIR models=4 size=128
Sheets:  root=DIR (a rendered chairs/cars root) out=docs/contact size=64: one sheet per source package
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from nvs.core.errors import UserError

from nvs.run.cli import exits_cleanly

_INT_KEYS = {"size", "seed", "max_models", "sequences", "frames", "supersample", "pairs_per_model", "models",
             "workers"}
_KEYS = {
    "chairs": {"size", "out", "seed", "max_models", "supersample", "pairs_per_model", "workers", "assets"},
    "cars": {"size", "out", "seed", "max_models", "supersample", "pairs_per_model", "workers", "assets"},
    "drive": {"size", "out", "seed", "sequences", "frames", "supersample", "sources", "camera"},
    "contact": {"out", "chairs", "cars", "drive", "models", "size"},
    "sheets": {"root", "out", "size"},
}


def parse(argv: list[str]) -> tuple[str, dict]:
    if not argv or argv[0] not in _KEYS:
        raise UserError(f"usage: python -m nvs.data.render <{'|'.join(_KEYS)}> [key=value ...]\n{__doc__}")
    what, opts = argv[0], {}
    for arg in argv[1:]:
        key, sep, value = arg.partition("=")
        if not sep or key not in _KEYS[what]:
            raise UserError(f"unknown option {arg!r} for {what}; known: {', '.join(sorted(_KEYS[what]))}")
        if key in _INT_KEYS:
            try:
                opts[key] = int(value)
            except ValueError:
                raise UserError(f"{key} must be an integer, got {value!r}") from None
        else:
            opts[key] = value
    if opts.get("workers", 1) < 1:
        raise UserError(f"workers must be >= 1, got {opts['workers']}")
    if "supersample" in opts and opts["supersample"] % 2 == 0:
        raise UserError("supersample must be odd (depth is the centre sample of each block)")
    return what, opts


@exits_cleanly
def main(argv: list[str] | None = None) -> None:
    what, opts = parse(sys.argv[1:] if argv is None else argv)
    if what == "sheets":
        from nvs.data.render.contact import write_source_sheets

        if "root" not in opts:
            raise UserError("sheets needs root=DIR (a rendered chairs or cars root)")
        try:
            paths = write_source_sheets(Path(opts["root"]), Path(opts.get("out", "docs/contact")), opts.get("size", 64))
        except FileNotFoundError as err:
            raise UserError(str(err)) from None
        print("wrote " + " ".join(str(p) for p in paths))
        return
    if what == "contact":
        from nvs.data.render.contact import write_contact_sheet

        roots = {k: Path(opts[k]) for k in ("chairs", "cars", "drive") if k in opts}
        if not roots:
            raise UserError("contact needs at least one of chairs=DIR cars=DIR drive=DIR")
        path = write_contact_sheet(Path(opts.get("out", "docs/contact_sheet.png")), roots.get("chairs"),
                                   roots.get("cars"), roots.get("drive"), opts.get("models", 4),
                                   opts.get("size", 128))
        print(f"wrote {path}")
        return
    size = opts.pop("size", 256)
    out = Path(opts.pop("out", f"data/{what}_{size}"))
    if what == "drive":
        from nvs.data.render.drive import render_drive

        render_drive(out, size=size, **opts)
    else:
        from nvs.data.render.sources import ASSETS_ENV, asset_dir

        assets = asset_dir(opts.pop("assets", None), os.environ.get(ASSETS_ENV))  # before anything is loaded
        if not assets.is_dir():
            print(f"render: no extracted asset packages in {assets} (scripts/install_object_assets.sh, assets=DIR "
                  f"or ${ASSETS_ENV}): the installed Debian packages' models only", flush=True)
        from nvs.data.render.objects import render_objects

        opts.setdefault("workers", min(2, os.cpu_count() or 1))
        render_objects(what, out, size=size, assets=assets, **opts)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
