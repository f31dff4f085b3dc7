"""Layer 5, reports drawn from finished runs: the paper-style figures and point clouds."""
