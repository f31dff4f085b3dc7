"""Atomic writers for rendered views: PNG images and .npy depth maps (temp name, then os.replace)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image

from nvs.core.atomic import write_bytes


def write_png(path: Path, rgb: np.ndarray) -> None:
    """RGB (H,W,3) uint8 -> 8-bit RGB PNG, written atomically."""
    buf = io.BytesIO()
    Image.fromarray(rgb, mode="RGB").save(buf, format="PNG", optimize=False, compress_level=6)
    write_bytes(path, buf.getvalue())


def write_depth(path: Path, depth: np.ndarray) -> None:
    """Depth (H,W) -> float32 .npy, written atomically."""
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(depth, dtype=np.float32), allow_pickle=False)
    write_bytes(path, buf.getvalue())


def write_credits(root: Path, lines: list[str], packages: list[str], copyright_files: dict[str, Path]) -> None:
    """CREDITS.txt: one line per used model, then the copyright (licence) file of every package used."""
    text = ["Rendered with nvs.data.render from these packages' models. Licences and authors:", ""]
    text += lines
    for pkg in packages:
        f = copyright_files.get(pkg)
        text += ["", "=" * 100, f"{pkg}: {f}", "=" * 100]
        text.append(f.read_text(errors="replace") if f is not None and f.is_file() else "(copyright file missing)")
    write_bytes(root / "CREDITS.txt", ("\n".join(text) + "\n").encode())
