"""A matplotlib figure as PNG bytes, closed after: what every figure writer of nvs hands to an atomic write."""

from __future__ import annotations

import io


def figure_png(fig, dpi: int = 90, tight: bool = False) -> bytes:
    """The figure rendered at ``dpi`` (``tight``: cropped to its artists), then closed so that no figure piles up."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, **({"bbox_inches": "tight"} if tight else {}))
    plt.close(fig)
    return buf.getvalue()
