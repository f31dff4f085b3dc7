"""Moved to ``nvs.perceptual`` (the frozen VGG16 / LPIPS judges are not models of the method).

Kept only for ``tests/reference_code.py``, which still reads the weight loader from here.
"""

from nvs.perceptual import load_weights  # noqa: F401
