"""Layer 2, the loss terms: one class per term, (outputs, batch) -> scalar (``terms``), Sun et al.'s branches and adversarial term."""
