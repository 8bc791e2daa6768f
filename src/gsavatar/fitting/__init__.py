"""Fitting the body model to multi-view 2D keypoints (``avatar-prep fit-body``): keypoint formats, robust
triangulation, the batched fit, synthetic keypoints for checking it."""
