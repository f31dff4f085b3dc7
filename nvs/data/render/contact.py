"""Contact sheet: a grid of rendered views (rows = models or sequences) from dataset roots on disk."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from nvs.core.atomic import write_bytes

SHEET_AZIMUTHS = (0, 40, 100, 160, 220, 300)


def _tile(path: Path, size: int) -> Image.Image:
    with Image.open(path) as im:
        return im.convert("RGB").resize((size, size), Image.BICUBIC)


def object_rows(root: Path, models: int, size: int, elevation: int = 20) -> list[tuple[str, list[Image.Image]]]:
    """`models` evenly spaced models of a root (sorted ids, from meta.json when there), each at SHEET_AZIMUTHS."""
    meta = root / "meta.json"
    if meta.is_file():  # views of models a re-render no longer uses may still lie in images/
        ids = sorted(m["id"] for m in json.loads(meta.read_text())["models"])
    else:
        ids = sorted({p.stem.rsplit("_", 2)[0] for p in (root / "images").glob("*.png")})
    pick = [ids[int(i)] for i in np.linspace(0, len(ids) - 1, min(models, len(ids)))]
    return [(m, [_tile(root / "images" / f"{m}_{az}_{elevation}.png", size) for az in SHEET_AZIMUTHS])
            for m in pick]


def scene_rows(root: Path, sequences: int, size: int, columns: int = 6) -> list[tuple[str, list[Image.Image]]]:
    """The first `sequences` sequences of a scenes root, `columns` frames spread over each sequence."""
    frames: dict[str, list[str]] = {}
    for p in sorted((root / "images").glob("*.png")):
        frames.setdefault(p.stem.split("_")[0], []).append(p.stem)
    rows = []
    for seq in sorted(frames)[:sequences]:
        ids = frames[seq]
        pick = [ids[int(i)] for i in np.linspace(0, len(ids) - 1, columns)]
        rows.append((f"seq {seq}", [_tile(root / "images" / f"{i}.png", size) for i in pick]))
    return rows


def contact_sheet(rows: list[tuple[str, list[Image.Image]]], size: int) -> Image.Image:
    """Rows of equal-size tiles with a label strip above each row."""
    label = 14
    cols = max(len(r[1]) for r in rows)
    sheet = Image.new("RGB", (cols * size, len(rows) * (size + label)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for r, (name, tiles) in enumerate(rows):
        y = r * (size + label)
        draw.text((3, y + 1), name, fill=(0, 0, 0))
        for c, tile in enumerate(tiles):
            sheet.paste(tile, (c * size, y + label))
    return sheet


def write_contact_sheet(out: Path, chairs: Path | None, cars: Path | None, drive: Path | None,
                        models: int = 4, size: int = 128) -> Path:
    """Compose chairs / cars / drive rows (whichever roots are given) into one PNG at `out`."""
    rows = []
    for root in (chairs, cars):
        if root is not None:
            rows += object_rows(Path(root), models, size)
    if drive is not None:
        rows += scene_rows(Path(drive), models, size)
    buf = io.BytesIO()
    contact_sheet(rows, size).save(buf, format="PNG", optimize=True)
    write_bytes(out, buf.getvalue())
    return Path(out)


SOURCE_AZIMUTHS = (0, 60, 180)


def _model_cell(root: Path, model: str, size: int, elevation: int = 20) -> Image.Image:
    """One model: its id above views at SOURCE_AZIMUTHS (view (0, el) first: the model's front)."""
    label = 14
    cell = Image.new("RGB", (len(SOURCE_AZIMUTHS) * size, size + label), (255, 255, 255))
    ImageDraw.Draw(cell).text((3, 1), model[:len(SOURCE_AZIMUTHS) * size // 6], fill=(0, 0, 0))
    for c, az in enumerate(SOURCE_AZIMUTHS):
        cell.paste(_tile(root / "images" / f"{model}_{az}_{elevation}.png", size), (c * size, label))
    return cell


def source_sheet(root: Path, models: list[str], size: int = 64, per_row: int = 4) -> Image.Image:
    """Every model of `models` as a cell (id, views at SOURCE_AZIMUTHS), `per_row` cells per row."""
    cells = [_model_cell(root, m, size) for m in models]
    w, h = cells[0].size
    rows = (len(cells) + per_row - 1) // per_row
    sheet = Image.new("RGB", (min(per_row, len(cells)) * w, rows * h), (255, 255, 255))
    for i, cell in enumerate(cells):
        sheet.paste(cell, ((i % per_row) * w, (i // per_row) * h))
    return sheet


def write_source_sheets(root: Path, out_dir: Path, size: int = 64) -> list[Path]:
    """One PNG per source package of an object root (from its meta.json): <out_dir>/<category>_<package>.png."""
    root = Path(root)
    meta_path = root / "meta.json"
    if not meta_path.is_file():
        raise FileNotFoundError(f"{meta_path}: not a rendered object root (no meta.json)")
    meta = json.loads(meta_path.read_text())
    by_package: dict[str, list[str]] = {}
    for m in meta["models"]:
        by_package.setdefault(m["package"], []).append(m["id"])
    written = []
    for package, models in sorted(by_package.items()):
        buf = io.BytesIO()
        source_sheet(root, sorted(models), size).save(buf, format="PNG", optimize=True)
        path = Path(out_dir) / f"{meta['category']}s_{package}.png"
        write_bytes(path, buf.getvalue())
        written.append(path)
    return written
