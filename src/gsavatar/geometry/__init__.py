"""Geometry: rotations, forward kinematics and linear blend skinning, cameras, meshes."""
