"""Reading the files both dataset formats share: images, depth maps, id lists and pair lists.

Every failure raises ``DataError`` naming the file (and line).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError

from nvs.core.errors import DataError

# Modes that convert to RGB without losing meaning; anything else (16-bit, float, CMYK, 1-bit) is refused.
_ACCEPTED_MODES = {"RGB", "RGBA", "L", "P", "LA"}


def read_image(path: str | Path, size: int) -> torch.Tensor:
    """PNG/JPEG -> (3,size,size) uint8. Square images are resized (bicubic, antialiased); alpha is composited on white."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "image file is missing")
    try:
        with Image.open(path) as im:
            im.load()
            mode = im.mode
            if mode not in _ACCEPTED_MODES:
                raise DataError(path, f"unsupported image mode {mode!r} (expected 8-bit RGB, RGBA, L or P)")
            if im.width != im.height:
                raise DataError(path, f"image is {im.width}x{im.height}; expected a square image")
            if mode in ("RGBA", "LA", "P"):
                im = im.convert("RGBA")
                white = Image.new("RGBA", im.size, (255, 255, 255, 255))
                im = Image.alpha_composite(white, im)
            im = im.convert("RGB")
            if im.width != size:
                im = im.resize((size, size), Image.BICUBIC, reducing_gap=None)
            arr = np.asarray(im, dtype=np.uint8)
    except DataError:
        raise
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as err:
        raise DataError(path, f"cannot read image ({err.__class__.__name__}: {err})") from None
    return torch.from_numpy(arr.copy()).permute(2, 0, 1).contiguous()


def _dtype_problem(arr: np.ndarray) -> str | None:
    # An integer depth map is almost always a sensor's or renderer's millimetres (uint16): read as metres, every
    # depth metric would be 1000x off, so it is refused rather than guessed.
    if not np.issubdtype(arr.dtype, np.floating):
        return (f"depth is {arr.dtype}, expected float metres (an integer depth map is usually millimetres: "
                "save depth_mm / 1000.0 as float32)")
    return None


def read_depth(path: str | Path, size: int) -> torch.Tensor:
    """``.npy`` float depth in metres (0 = no data) -> (1,size,size) float32; resized by nearest-neighbour pooling.

    The one mask rule is 0 = no data: NaN, +-inf and negative depths are refused (DataError naming the file), not
    silently masked, because they usually mean a broken export rather than a deliberate hole.
    """
    path = Path(path)
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as err:
        raise DataError(path, f"cannot read depth ({err.__class__.__name__}: {err})") from None
    if arr.ndim != 2 or arr.shape[0] != arr.shape[1]:
        raise DataError(path, f"depth must be a square 2-D array, got shape {arr.shape}")
    problem = _dtype_problem(arr)
    if problem:
        raise DataError(path, problem)
    d = torch.from_numpy(np.asarray(arr, dtype=np.float32))
    bad = ~torch.isfinite(d) | (d < 0)
    if bad.any():
        masks = (("NaN", torch.isnan(d)), ("inf", torch.isinf(d)), ("negative", torch.isfinite(d) & (d < 0)))
        kinds = [k for k, m in masks if m.any()]
        raise DataError(path, f"{int(bad.sum())} depth value(s) are {'/'.join(kinds)}; depth must be finite metres "
                        ">= 0 (0 = no data): write 0 where there is no depth")
    n = d.shape[0]
    if n != size:
        if n % size:
            raise DataError(path, f"depth is {n}x{n}, not an integer multiple of the image size {size}")
        # Nearest (strided) pick: averaging would invent depths across object boundaries.
        f = n // size
        d = d[f // 2 :: f, f // 2 :: f]
    return d[None].contiguous()


def read_lines(path: str | Path) -> list[tuple[int, str]]:
    """Non-empty, non-comment lines with their 1-based line numbers."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "file is missing")
    try:
        # utf-8-sig: a byte-order mark (Windows editors write one) is not part of the first id
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as err:
        raise DataError(path, f"cannot read ({err})") from None
    out = []
    for i, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s and not s.startswith("#"):
            out.append((i, s))
    return out


def _read_records(path: str | Path, width: int, expected: str, what: str, known: set[str] | None = None) -> dict:
    """Lines of ``width`` whitespace-separated ids -> {record: 1-based line number}, in file order. A wrong width,
    an id outside ``known``, a duplicated record and an empty file are each one error naming the file and line."""
    seen: dict = {}
    for lineno, s in read_lines(path):
        parts = s.split()
        if len(parts) != width:
            raise DataError(path, f"expected {expected}, got {s!r}", lineno)
        record = parts[0] if width == 1 else tuple(parts)
        for pid in parts if known is not None else ():
            if pid not in known:
                raise DataError(path, f"unknown id {pid!r}", lineno)
        if record in seen:
            raise DataError(path, f"duplicated {what} {s!r} (first on line {seen[record]})", lineno)
        seen[record] = lineno
    if not seen:
        raise DataError(path, f"no {what}s: the split is empty")
    return seen


def read_id_lines(path: str | Path) -> dict[str, int]:
    """One id per line -> {id: 1-based line number}, in file order; duplicates and an empty list are errors."""
    return _read_records(path, 1, "one id per line", "id")


def read_ids(path: str | Path) -> list[str]:
    """One id per line; duplicates are an error."""
    return list(read_id_lines(path))


def read_pair_lines(path: str | Path, known: set[str] | None = None) -> dict[tuple[str, str], int]:
    """``idA idB`` per line (A = source, B = target) -> {(A, B): line number}. Unknown ids and duplicated pairs are
    errors."""
    return _read_records(path, 2, "'idA idB'", "pair", known)


def read_pairs(path: str | Path, known: set[str] | None = None) -> list[tuple[str, str]]:
    """``idA idB`` per line (A = source, B = target). Unknown ids and duplicated pairs are errors."""
    return list(read_pair_lines(path, known))


def image_problem(path: Path, header: bool) -> str | None:
    """Why ``path`` cannot be a view image (None if it looks fine): missing or empty, and with ``header`` an
    unreadable header, a refused mode, a non-square size or a truncated file. Decodes no pixels (~0.15 ms a file)."""
    try:
        if path.stat().st_size == 0:
            return "image file is empty"
    except OSError:
        return "image file is missing"
    if not header:
        return None
    try:
        with Image.open(path) as im:
            mode, w, h = im.mode, im.width, im.height
            im.verify()  # chunk checksums, to the end of the file: catches truncation without decoding pixels
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as err:
        return f"cannot read image ({err.__class__.__name__}: {err})"
    if mode not in _ACCEPTED_MODES:
        return f"unsupported image mode {mode!r} (expected 8-bit RGB, RGBA, L or P)"
    if w != h:
        return f"image is {w}x{h}; expected a square image"
    return None


def depth_problem(path: Path, size: int) -> str | None:
    """Why ``path`` cannot be a depth map for images of ``size`` (None if it fits); reads the .npy header only."""
    if not path.is_file():
        return "depth file is missing"
    try:
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, EOFError) as err:
        return f"cannot read depth ({err.__class__.__name__}: {err})"
    if arr.ndim != 2 or arr.shape[0] != arr.shape[1]:
        return f"depth must be a square 2-D array, got shape {arr.shape}"
    if _dtype_problem(arr):
        return _dtype_problem(arr)
    if arr.shape[0] != size and arr.shape[0] % size:
        return f"depth is {arr.shape[0]}x{arr.shape[0]}, not an integer multiple of the image size {size}"
    return None


def parse_float(token: str, path: Path, lineno: int, what: str) -> float:
    try:
        v = float(token)
    except ValueError:
        raise DataError(path, f"{what} {token!r} is not a number", lineno) from None
    if not math.isfinite(v):
        raise DataError(path, f"{what} is not finite ({token})", lineno)
    return v
