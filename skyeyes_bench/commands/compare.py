"""`skyeyes-bench compare A.json B.json`: paired comparison of two results."""

from __future__ import annotations


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
    p.set_defaults(handler="skyeyes_bench.commands._compare_impl:compare_cmd")
