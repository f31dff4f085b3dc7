"""Layer 0, the contract: batch and output types with shapes, camera geometry, metric spec, errors, atomic writes."""
