"""Layer 2, per-image metrics: every function returns a (B,) tensor (``per_image``)."""
