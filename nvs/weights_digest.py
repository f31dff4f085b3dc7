"""A content hash of a checkpoint's weights, stored when it is written and checked whenever it is read.

A zip member's CRC only says the bytes match what the zip writer saw; torch does not check it on load, and a CRC
recomputed after an edit passes. The hash covers every tensor's key, dtype, shape and values (in logical order, so a
channels_last tensor and its contiguous copy hash alike).
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from pathlib import Path

import torch

from nvs.errors import UserError

KEY = "nvs_weights_sha256"


def digest(state_dict: Mapping[str, torch.Tensor]) -> str:
    """sha256 hex digest of a state_dict (keys sorted; non-tensor entries by their repr)."""
    h = hashlib.sha256()
    for key in sorted(state_dict):
        value = state_dict[key]
        h.update(key.encode() + b"\0")
        if not torch.is_tensor(value):
            h.update(repr(value).encode() + b"\0")
            continue
        t = value.detach().cpu().contiguous().reshape(-1)
        h.update(f"{t.dtype}{tuple(value.shape)}\0".encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def stamp(checkpoint: dict) -> None:
    """Store the digest of ``checkpoint["state_dict"]`` in the checkpoint (at save time)."""
    checkpoint[KEY] = digest(checkpoint["state_dict"])


def verify(checkpoint: dict, path: str | Path) -> bool:
    """True when the stored digest matches the weights, False when the checkpoint holds none (written before nvs
    stored one); a mismatch is a UserError naming the file."""
    stored = checkpoint.get(KEY)
    if stored is None:
        return False
    if digest(checkpoint.get("state_dict") or {}) != stored:
        raise UserError(f"{path}: corrupt checkpoint (its weights do not match the content hash stored when it was "
                        "written); use another checkpoint or retrain")
    return True
