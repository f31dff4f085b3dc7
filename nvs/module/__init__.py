"""Layer 3, the one LightningModule (``lightning_module.NVSModule``) and its gathering of per-pair rows across ranks."""
