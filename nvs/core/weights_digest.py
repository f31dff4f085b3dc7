"""A content hash of a checkpoint's weights, stored when it is written and checked whenever it is read.

A zip member's CRC only says the bytes match what the zip writer saw; torch does not check it on load, and a CRC
recomputed after an edit passes. The hash covers every tensor's key, dtype, shape, memory layout and values
(torch.save and torch.load keep a tensor's layout: the tensors hashed at save time are those hashed at load time).
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from pathlib import Path

import torch

from nvs.core.errors import UserError

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
        t, layout = _dense(value.detach().cpu())
        h.update(f"{t.dtype}{tuple(value.shape)}{layout}\0".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy() if t.numel() else b"")  # the buffer itself, no copy
    return h.hexdigest()


def _dense(t: torch.Tensor) -> tuple[torch.Tensor, str]:
    """``t`` as a contiguous tensor over the same memory where it is one (a channels_last weight is its NHWC
    permutation: copying it to NCHW would cost more than the hash), and the layout's name."""
    if t.is_contiguous():
        return t, ""
    if t.dim() == 4 and t.is_contiguous(memory_format=torch.channels_last):
        return t.permute(0, 2, 3, 1), "nhwc"
    return t.contiguous(), ""


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
