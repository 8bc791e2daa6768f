"""Small shared utilities: atomic file writes, image IO, progress bars."""
