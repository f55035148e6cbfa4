"""`skyeyes-bench compare A.json B.json`: paired comparison of two results."""

from __future__ import annotations

import json
import sys


def register(sub) -> None:
    p = sub.add_parser("compare", help="is method A credibly better than B? (paired, per sequence)",
                       description="Paired comparison of two results of the same protocol and ground truth: "
                       "per metric the mean per-sequence advantage of A (> 0: A better), its clustered "
                       "bootstrap interval, and a Bayesian Student-t model (emcee) giving P(A better) and a "
                       "95%% HDI. Set metrics (FID, KID, FVD, KVD) by the paired bootstrap only.")
    p.add_argument("a", metavar="A.json", help="results of method A")
    p.add_argument("b", metavar="B.json", help="results of method B")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--out", metavar="FILE", help="also write the comparison JSON here")
    p.set_defaults(run=run)


def _fmt(v) -> str:
    return "n/a" if v is None else f"{v:.4g}"


def run(args) -> int:
    from .. import fileio
    from ..evaluate import read_results
    from ..stats import compare_results

    if args.out:  # before any work; compare's output is replaced freely, but never an input
        fileio.check_output(args.out, force=True, inputs=[args.a, args.b], inputs_are="the results being compared")
    a, fa = read_results(args.a, features=False)
    b, fb = read_results(args.b, features=False)
    sets = any(m.get("kind") == "set" and m["status"] == "ok" for m in a["metrics"].values())
    if sets:  # set metrics need the features sidecars; without them they are skipped, and said so
        try:
            _, fa = read_results(args.a, features=True)
            _, fb = read_results(args.b, features=True)
        except Exception as e:  # noqa: BLE001 - report and continue with per-frame metrics
            print(f"skyeyes-bench: warning: {e}", file=sys.stderr)
            fa = fb = None
    res = compare_results(a, b, fa, fb)
    if args.out:
        fileio.write_json(args.out, res)
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    print(f"A = {res['a']}  vs  B = {res['b']}  on {res['protocol']} ({res['sequences']} sequences)")
    print("advantage of A: > 0 means A is better (A - B for PSNR/SSIM, B - A for LPIPS/FID/KID/FVD/KVD)")
    for name, m in res["metrics"].items():
        if m["status"] != "ok":
            print(f"  {name:<6} skipped: {m['note']}")
            continue
        lo, hi = m["bootstrap_interval"] or (None, None)
        line = (f"  {name:<6} A {_fmt(m['a'])}  B {_fmt(m['b'])}  advantage {_fmt(m['advantage_mean'])}  "
                f"bootstrap {int(m['level'] * 100)}% [{_fmt(lo)}, {_fmt(hi)}]")
        bz = m["bayes"]
        if bz.get("fitted"):
            line += (f"  P(A better) {bz['p_a_better']:.3f}  HDI95 [{_fmt(bz['hdi'][0])}, {_fmt(bz['hdi'][1])}]")
            for w in bz.get("warnings", []):
                print(f"skyeyes-bench: warning: {name}: {w}", file=sys.stderr)
        elif "p_a_better_bootstrap" in m:
            line += f"  P(A better, bootstrap) {_fmt(m['p_a_better_bootstrap'])}"
        elif bz.get("hdi") is not None:
            line += f"  P(A better) {_fmt(bz['p_a_better'])}  ({bz['note']})"
        else:
            line += f"  ({bz['note']})"
        print(line)
    return 0
