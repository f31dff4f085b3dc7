"""Videos of a camera path: each frame is the synthesised view with its predicted depth beside it; MP4 and GIF.

The depth panel uses one near/far range for the whole video (grey, near = bright), so brightness changes are depth
changes, not a per-frame stretch. MP4 is H.264 through the ffmpeg binary the ``imageio-ffmpeg`` wheel ships; GIF is
written by Pillow. Models without depth get the view alone.
"""

from __future__ import annotations

import io
import tempfile
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from PIL import Image
from tqdm import tqdm

from nvs.core.errors import UserError
from nvs.viewer.session import View, ViewSession


def render_views(session: ViewSession, key: str, path: list[dict[str, float]], progress: bool = True) -> list[View]:
    """The view of source ``key`` at every pose of ``path`` (control values), with a progress bar."""
    bar = tqdm(path, desc="render video", unit="frame", disable=not progress, leave=False)
    return [session.view(key, values) for values in bar]


def compose_frames(views: list[View], scale: int = 2) -> list[np.ndarray]:
    """(H*scale, W*scale*panels, 3) uint8 frames: view | depth (nearest-neighbour upscaling keeps 64² crisp)."""
    depths = [v.depth_values for v in views if v.depth_values is not None]
    span = (min(float(d.min()) for d in depths), max(float(d.max()) for d in depths)) if depths else None
    frames = []
    for v in views:
        panels = [v.rgb]
        if v.depth_values is not None:
            panels.append(np.repeat(depth_grey(v.depth_values, span)[..., None], 3, axis=2))
        frame = np.concatenate(panels, axis=1)
        frames.append(np.ascontiguousarray(frame.repeat(scale, axis=0).repeat(scale, axis=1)))
    return frames


def depth_grey(depth: np.ndarray, span: tuple[float, float]) -> np.ndarray:
    """(H,W) depth -> (H,W) uint8, near = bright, over the fixed ``span`` = (near, far)."""
    lo, hi = span
    scaled = (hi - depth) / (hi - lo) if hi > lo else np.full_like(depth, 0.5)
    return (np.clip(scaled, 0.0, 1.0) * 255.0).round().astype(np.uint8)


def write_mp4(out: Path, frames: list[np.ndarray], fps: float) -> Path:
    """H.264 MP4 (yuv420p, plays in browsers); frame sides must be even (the model sizes are multiples of 16)."""
    import imageio_ffmpeg

    h, w = frames[0].shape[:2]
    if h % 2 or w % 2:
        raise UserError(f"frames of {w}x{h}: H.264 needs even sides")
    out.parent.mkdir(parents=True, exist_ok=True)
    writer = imageio_ffmpeg.write_frames(str(out), (w, h), fps=fps, codec="libx264", pix_fmt_in="rgb24",
                                         pix_fmt_out="yuv420p", quality=8, macro_block_size=1,
                                         ffmpeg_log_level="error")
    writer.send(None)  # start the ffmpeg process
    try:
        for frame in frames:
            writer.send(frame)
    finally:
        writer.close()
    return out


def write_gif(out: Path | io.BytesIO, frames: list[np.ndarray], fps: float, colors: int = 256) -> Path | io.BytesIO:
    """Looping GIF, one adaptive palette of ``colors`` (2..256; fewer: a smaller file) per frame.

    GIF stores frame durations in 1/100 s, so the frame rate is rounded to that.
    """
    if not 2 <= colors <= 256:
        raise UserError(f"gif colors={colors}: expected 2..256")
    images = [Image.fromarray(f).quantize(colors=colors, method=Image.Quantize.MEDIANCUT) for f in frames]
    if isinstance(out, Path):
        out.parent.mkdir(parents=True, exist_ok=True)
    images[0].save(out, format="GIF", save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0)
    return out


def write_video(out_stem: Path, frames: list[np.ndarray], fps: float, formats: Iterable[str],
                gif_colors: int = 256) -> list[Path]:
    """``<out_stem>.mp4`` and/or ``<out_stem>.gif``."""
    written = []
    for fmt in formats:
        if fmt == "mp4":
            written.append(write_mp4(out_stem.with_suffix(".mp4"), frames, fps))
        elif fmt == "gif":
            written.append(write_gif(out_stem.with_suffix(".gif"), frames, fps, gif_colors))
        else:
            raise UserError(f"formats: {fmt!r} is not one of mp4, gif")
    return written


def video_bytes(frames: list[np.ndarray], fps: float) -> dict[str, bytes]:
    """Both formats in memory (the viewer's button): {"mp4": ..., "gif": ...}."""
    gif = write_gif(io.BytesIO(), frames, fps).getvalue()
    with tempfile.TemporaryDirectory() as tmp:  # ffmpeg writes MP4 to a seekable file (the index at the end)
        mp4 = write_mp4(Path(tmp) / "v.mp4", frames, fps).read_bytes()
    return {"mp4": mp4, "gif": gif}
