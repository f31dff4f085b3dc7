"""python -m mynvs.turntable SRC OUT [--category chair] [--test N]: a turntable dataset -> nvs's objects format.

The "turntable" format of this example: one folder per object, images named ``az<azimuth>_el<elevation>.png``
(degrees; the azimuths 0..340 in steps of 20 and elevations 0, 10, 20 of the objects format), the camera looking at
the object centre from distance 2 as in docs/datasets.md. The converter writes the on-disk objects format
(``images/{model}_{az}_{el}.png``, ``id_train.txt``, ``id_val.txt``, ``eval_{category}_40.txt``), which nvs reads
unchanged; the last ``--test`` objects become the test split, its pairs 20° apart.
"""

from __future__ import annotations

import argparse
import re
import shutil
from pathlib import Path

NAME = re.compile(r"az(\d+)_el(\d+)\.png$")


def convert(src: Path, out: Path, category: str = "chair", test: int = 1) -> dict[str, list[str]]:
    objects = sorted(p.name for p in src.iterdir() if p.is_dir())
    if len(objects) < test + 2:
        raise SystemExit(f"{src}: {len(objects)} objects; need at least {test + 2} (train, val, test)")
    (out / "images").mkdir(parents=True, exist_ok=True)
    views: dict[str, list[tuple[int, int]]] = {}
    for obj in objects:
        for image in sorted((src / obj).glob("*.png")):
            m = NAME.search(image.name)
            if not m:
                raise SystemExit(f"{image}: expected az<deg>_el<deg>.png")
            az, el = int(m.group(1)), int(m.group(2))
            shutil.copyfile(image, out / "images" / f"{obj}_{az}_{el}.png")
            views.setdefault(obj, []).append((az, el))
    split = {"train": objects[:-test - 1], "val": objects[-test - 1:-test], "test": objects[-test:]}
    (out / "id_train.txt").write_text("\n".join(split["train"]) + "\n")
    (out / "id_val.txt").write_text("\n".join(split["val"]) + "\n")
    (out / "id_test.txt").write_text("\n".join(split["test"]) + "\n")
    pairs = []
    for obj in split["test"]:
        have = set(views[obj])
        for az, el in sorted(have):
            if ((az + 20) % 360, el) in have:
                pairs.append(f"{obj}_{az}_{el} {obj}_{(az + 20) % 360}_{el}")
    (out / f"eval_{category}_40.txt").write_text("\n".join(pairs) + "\n")
    return split


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--category", default="chair")
    ap.add_argument("--test", type=int, default=1)
    args = ap.parse_args()
    split = convert(args.src, args.out, args.category, args.test)
    print(f"wrote {args.out}: " + ", ".join(f"{k} {len(v)} objects" for k, v in split.items()))


if __name__ == "__main__":
    main()
