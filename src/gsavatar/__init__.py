"""gsavatar: drivable 3D Gaussian human avatars with autoregressive appearance prediction.

Subpackages, low layer to high (each imports only lower ones; docs/architecture.md):
``utils`` (files, JSON, CLI helpers, ``SchemaError``), ``geometry`` (rotations, skinning,
cameras, meshes), ``data_schema`` (capture format v1, every prepared-dataset artifact and its
reader), ``render`` (Gaussian rasterization), ``metrics``, ``motion`` (BVH, retargeting,
frame-rate resampling), ``models``, ``runs`` (a trained run: config, checkpoints, loading,
rendering views), ``prep`` (the ``avatar-prep`` stages), ``synth`` (synthetic captures from a
real body model and real mocap), ``train``, ``drive``.
"""

__version__ = "0.1.0"
