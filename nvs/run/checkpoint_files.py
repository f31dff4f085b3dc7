"""Checkpoint files as files: whole or not, their content hash, their recorded step, which one a run resumes from.

:func:`read_checkpoint` is the one way nvs opens a checkpoint: resume, the test after training, ``nvs.evaluate``, the
viewer and ``nvs.figures`` (through :func:`nvs.run.checkpoints.load_checkpoint`) all read through it.
"""

from __future__ import annotations

import sys
import zipfile
from pathlib import Path

import torch

from nvs.core.errors import UserError
from nvs.core.weights_digest import verify


def check_complete(path: str | Path) -> None:
    """UserError unless ``path`` is a whole zip whose every member passes its CRC (a kill or flipped bytes)."""
    # torch.save writes a zip whose directory sits at the end: a write cut short by a kill has none.
    if not zipfile.is_zipfile(path):
        raise UserError(f"{path}: incomplete checkpoint (the run was probably killed while writing it); "
                        "delete it to resume from scratch, or pass ckpt_path=<another checkpoint>")
    try:  # every member's CRC: flipped bytes inside an intact zip would otherwise fail deep inside unpickling
        with zipfile.ZipFile(path) as zf:
            bad = zf.testzip()
    except (zipfile.BadZipFile, OSError, EOFError) as err:
        bad = f"({err})"
    if bad:
        raise UserError(f"{path}: corrupt checkpoint (member {bad} fails its checksum); delete it to resume from "
                        "scratch, or pass ckpt_path=<another checkpoint>")


def read_checkpoint(path: str | Path, mmap: bool = False) -> dict:
    """The checkpoint dict at ``path`` (on the CPU), checked whole: zip, CRCs, the weights' content hash.

    A file that is none, or fails a check, is a UserError naming it; one without a hash (written before nvs stored
    one, or an older ``nvs.convert``) loads with a one-line notice.
    """
    p = Path(path)
    if not p.is_file():
        raise UserError(f"ckpt_path={path}: no such checkpoint")
    if zipfile.is_zipfile(p):  # (torch's legacy format is no zip: torch.load judges it)
        check_complete(p)
    try:
        ckpt = torch.load(p, map_location="cpu", weights_only=False, mmap=mmap)
    except Exception as err:  # noqa: BLE001 - any unpickling failure is a bad file for the user
        raise _unreadable(p, err) from None
    if isinstance(ckpt, dict) and not verify(ckpt, p) and _rank_zero():
        print(f"note: {path} holds no content hash of its weights (written before nvs stored one): loaded "
              "unverified", file=sys.stderr)
    return ckpt


def _unreadable(path: Path, err: Exception) -> UserError:
    if not zipfile.is_zipfile(path):  # torch's format is a zip; this is no zip, nor a legacy file torch could read
        return UserError(f"{path}: not a readable checkpoint: incomplete (no zip directory: a write cut short, e.g. "
                         "by a kill) or another kind of file; pass ckpt_path=<another checkpoint>")
    first = next((ln.strip() for ln in str(err).splitlines() if ln.strip()), "")
    return UserError(f"{path}: not a readable checkpoint ({err.__class__.__name__}: {first[:300]})")


def _rank_zero() -> bool:
    from lightning.pytorch.utilities.rank_zero import rank_zero_only

    return getattr(rank_zero_only, "rank", 0) == 0


def step_of(path: Path) -> int:
    """The global step a checkpoint records (read without loading its tensors); UserError for a broken file."""
    if not zipfile.is_zipfile(path):
        check_complete(path)
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False, mmap=True)
    except Exception as err:  # noqa: BLE001 - any unpickling failure is a bad file for the user
        raise _unreadable(Path(path), err) from None
    return int(ckpt.get("global_step", 0)) if isinstance(ckpt, dict) else 0


def newest_checkpoint(directory: str | Path) -> tuple[Path, int] | None:
    """The checkpoint in ``directory`` with the highest recorded step (a ``last`` one on a tie), and that step.

    Names decide nothing: a run resumed in a moved directory by an older nvs may hold ``last-v1.ckpt`` ahead of
    ``last.ckpt``; a best checkpoint can be ahead of a stale last.
    """
    found = [(step_of(p), p.name.startswith("last"), p) for p in sorted(Path(directory).glob("*.ckpt"))
             if not p.name.startswith(".")]
    if not found:
        return None
    step, _, path = max(found, key=lambda f: (f[0], f[1], f[2].name == "last.ckpt"))
    return path, step


def resume_checkpoint(ckpt_path: str | None, directory: str | Path) -> tuple[str, int] | None:
    """What a run resumes from, checked whole (:func:`read_checkpoint`): ``ckpt_path`` itself, or for ``auto`` the
    newest checkpoint in ``directory``; None to start afresh. Returns the path and its recorded step."""
    if ckpt_path in (None, "none", "null"):
        return None
    if ckpt_path == "auto":
        newest = newest_checkpoint(directory)
        if newest is None:
            return None
        path = newest[0]
    else:
        path = Path(ckpt_path)
        if not path.is_file():
            raise UserError(f"ckpt_path={ckpt_path}: no such checkpoint")
    check_complete(path)  # what a kill during a write leaves is named as such
    ckpt = read_checkpoint(path, mmap=True)
    return str(path), int(ckpt.get("global_step", 0)) if isinstance(ckpt, dict) else 0


def held_precision(path: str | None) -> dict | None:
    """The precision choice a run recorded in its checkpoint at ``path`` (``PrecisionRecord``'s state), or None
    (no path, a checkpoint written before the record, or one that does not read: the resume itself reports that)."""
    if path is None:
        return None
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False, mmap=True)
    except Exception:  # noqa: BLE001 - read whole and reported by resume_checkpoint; here only the record matters
        return None
    record = (ckpt.get("callbacks") or {}).get("PrecisionRecord") if isinstance(ckpt, dict) else None
    return dict(record) if isinstance(record, dict) else None
