"""Layer 4, a run as a library call: config to objects, training, checkpoints, callbacks, run artifacts."""
