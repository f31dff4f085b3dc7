"""Images in and out of the viewer: uploads -> the model's square input, tensors -> PNG data URLs for the page."""

from __future__ import annotations

import base64
import io

import numpy as np
import torch
from PIL import Image, ImageOps, UnidentifiedImageError

from nvs.core.errors import UserError

# A 48-megapixel phone photo fits; decoded as RGBA that is ~200 MB, the most one upload may cost the viewer.
MAX_UPLOAD_PIXELS = 50_000_000


def decode_upload(data: bytes, size: int, name: str = "upload") -> torch.Tensor:
    """Any image PIL reads -> (3,size,size) uint8: EXIF orientation applied, alpha on white, centre-cropped, resized.

    A file that is not a readable image is one UserError naming it.
    """
    if not data:
        raise UserError(f"{name}: the file is empty")
    try:
        with Image.open(io.BytesIO(data)) as im:
            # The header's size, before any pixel is decoded: a small file can declare gigabytes of pixels.
            if im.width * im.height > MAX_UPLOAD_PIXELS:
                raise UserError(f"{name}: image too large ({im.width}x{im.height} pixels; the viewer takes at most "
                                f"{MAX_UPLOAD_PIXELS // 10**6} megapixels)")
            im.load()
            im = ImageOps.exif_transpose(im)
            if im.mode in ("RGBA", "LA", "PA") or (im.mode == "P" and "transparency" in im.info):
                rgba = im.convert("RGBA")
                im = Image.alpha_composite(Image.new("RGBA", rgba.size, (255, 255, 255, 255)), rgba)
            im = ImageOps.fit(im.convert("RGB"), (size, size), Image.BICUBIC)
            arr = np.asarray(im, dtype=np.uint8)
    except Image.DecompressionBombError as err:
        raise UserError(f"{name}: image too large ({err})") from None
    except UnidentifiedImageError:
        raise UserError(f"{name} is not an image (no image format Pillow reads: PNG, JPEG, WebP, ...)") from None
    except (OSError, SyntaxError, ValueError) as err:
        raise UserError(f"{name}: the image cannot be read ({err.__class__.__name__}: {err})") from None
    return torch.from_numpy(arr.copy()).permute(2, 0, 1).contiguous()


def to_uint8(img: torch.Tensor) -> np.ndarray:
    """(3,H,W) float in [0,1] or uint8 -> (H,W,3) uint8."""
    if img.dtype != torch.uint8:
        img = (img.float().clamp(0, 1) * 255.0).round().to(torch.uint8)
    return img.permute(1, 2, 0).contiguous().numpy()


def depth_to_uint8(depth: torch.Tensor) -> tuple[np.ndarray, tuple[float, float]]:
    """(1,H,W) depth -> (H,W) uint8 grey, near = bright, stretched over this view's range; and that range."""
    d = depth[0].float()
    lo, hi = float(d.min()), float(d.max())
    scaled = (hi - d) / (hi - lo) if hi > lo else torch.full_like(d, 0.5)
    return (scaled * 255.0).round().to(torch.uint8).numpy(), (lo, hi)


def png_data_url(arr: np.ndarray) -> str:
    """(H,W,3) or (H,W) uint8 -> 'data:image/png;base64,...' (fastest zlib level: the page is local)."""
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="PNG", compress_level=1)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")
