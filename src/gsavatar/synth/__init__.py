"""Synthetic captures from a real body model (anny) and real mocap (CMU BVH)."""
