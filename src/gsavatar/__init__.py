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

import os as _os

# After every parallel op torch's idle OpenMP workers spin (libgomp's default: 300,000 iterations) on the
# cores our compiled kernels' threads need (2 threads on the 2-core box, live Gaussians: median 29.2 ->
# 33.3 frames/s with 10,000, docs/drive.md). libgomp reads this when torch loads it, so it is set before
# anything here imports torch; a value the user set wins.
_os.environ.setdefault("GOMP_SPINCOUNT", "10000")
