"""gsavatar: drivable 3D Gaussian human avatars with autoregressive appearance prediction.

Subpackages: ``data_schema`` (capture format v1 and derived datasets),
``geometry`` (rotations, skinning, cameras, meshes), ``synth`` (synthetic captures
from a real body model and real mocap), ``prep`` (the ``avatar-prep`` stages),
``render`` (Gaussian rasterization), ``models``, ``train``, ``drive``.
"""

__version__ = "0.1.0"
