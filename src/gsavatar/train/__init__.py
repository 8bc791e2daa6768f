"""Training: loss terms (``losses``) and, elsewhere in this package, the training loop."""
