"""The numerical stress report (``python -m nvs.stress``), one module per report section.

harness (finiteness, quiet logs), batches (the batches every section feeds), options (the model options it builds),
geometry, gradcheck, precision, training, determinism (the sections), report (tables, provenance, the CLI).
"""

from nvs.stress.report import main

__all__ = ["main"]
