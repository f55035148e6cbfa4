"""`skyeyes-bench compare A.json B.json`: paired comparison of two results."""

from __future__ import annotations

import json
import sys


def register(sub) -> None:
    p = sub.add_parser("compare", help="is method A credibly better than B? (paired, per scene)",
                       description="Paired comparison of two results of the same protocol and ground truth: "
                       "per metric the values of A and B exactly as `evaluate` reported them, the advantage of A "
                       "(their difference, > 0: A better), its interval from paired half-sampling of the "
                       "protocol's clusters (scenes; the same clusters for A and B), and for per-frame metrics a "
                       "Bayesian Student-t model (emcee) of per-cluster differences giving P(A better) and a "
                       "95% HDI. Below 5 clusters: no interval and no P(better) ('too few scenes'). Set metrics "
                       "use the replicates stored in the results; the .features.npz sidecars are read only for "
                       "older results without them (absent: those metrics are skipped, and said so). When both "
                       "files come from runs of several seeds (reproduce --seeds N), each metric also gets a t test "
                       "on the seeds' values (paired by seed when both ran the same seeds, else Welch's): does "
                       "the difference exceed the spread between seeds? A progress "
                       "bar appears on a terminal when it takes more than 2 s.")
    p.add_argument("a", metavar="A.json", help="results of method A")
    p.add_argument("b", metavar="B.json", help="results of method B")
    p.add_argument("--json", action="store_true", help="print the comparison JSON instead of the summary")
    p.add_argument("--out", metavar="FILE", help="also write the comparison JSON here")
    p.set_defaults(run=run)


#: One line on what the Student-t summary describes (comparison.BAYES_ESTIMAND says it in full).
BAYES_NOTE = ("location of a robust model of per-{unit} differences of per-{unit} frame means; it may differ "
              "from the advantage above when {unit}s differ in frame count or one {unit} is an outlier")


def _fmt(v) -> str:
    return "n/a" if v is None else f"{v:.4g}"


def _abd(a: float, b: float, adv: float, higher: bool) -> tuple[str, str, str]:
    """A, B and the advantage printed so that the advantage is the difference of the printed A and B
    (A - B, or B - A where lower is better): all three at the same number of decimals."""
    import math

    finite = [abs(v) for v in (a, b) if math.isfinite(v)]
    mag = max(finite, default=0.0)
    # 4 significant digits of the larger value, and at least 1 of a small advantage
    dec = max(0, 3 - int(math.floor(math.log10(mag)))) if mag > 0 else 4
    if math.isfinite(adv) and adv != 0:
        dec = max(dec, min(12, 1 - int(math.floor(math.log10(abs(adv))))))

    def f(v):
        return "n/a" if v is None else ("inf" if v == math.inf else "-inf" if v == -math.inf else f"{v:.{dec}f}")

    if all(map(math.isfinite, (a, b))):
        ra, rb = round(a, dec), round(b, dec)
        adv = (ra - rb if higher else rb - ra) + 0.0  # the difference of what is printed (no -0)
    return f(a), f(b), f(adv)


def _seed_list(seeds: list[int]) -> str:
    return f"{len(seeds)} seeds ({', '.join(map(str, seeds))})"


def _print_seeds(m: dict) -> None:
    """The seed test of one metric (`seeds.seed_test`) as a line under it, if there is one."""
    t = m.get("seeds")
    if t is None:
        return
    if t["status"] != "ok":
        print(f"         seeds: {t['note']}")
        return
    lo, hi = t["interval"]
    df = "" if t["df"] is None else f", df {t['df']:.3g}"
    print(f"         seeds: A {_fmt(t['a_mean'])} sd {_fmt(t['a_sd'])} (n={t['n_a']}), B {_fmt(t['b_mean'])} sd "
          f"{_fmt(t['b_sd'])} (n={t['n_b']}); advantage {_fmt(t['advantage'])} se {_fmt(t['se'])}, "
          f"{int(t['level'] * 100)}% {'paired t' if t['test'] == 'paired' else 'Welch'} [{_fmt(lo)}, {_fmt(hi)}]{df}: "
          f"{t['verdict']}")


def run(args) -> int:
    from ..api import compare

    res = compare(args.a, args.b, out=args.out, progress=True)  # a bar only on a terminal, after 2 s
    for w in res.get("warnings", []):
        print(f"skyeyes-bench: warning: {w}", file=sys.stderr)
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    unit = res["cluster"]
    print(f"A = {res['a']}  vs  B = {res['b']}  on {res['protocol']} ({res['clusters']} {unit}s, "
          f"{res['sequences']} sequences; intervals: {res['interval']} of {unit}s)")
    print("A, B: the values `evaluate` reports; advantage of A = their difference, > 0 means A is better "
          "(A - B for PSNR/SSIM, B - A for LPIPS/FID/KID/FVD/KVD)")
    if res["too_few"]:
        print(f"  {res['too_few']}: no intervals and no P(A better) (they need at least 5 {unit}s)")
    seeds = res.get("seeds")
    from ..seeds import SEED_TEST_PAIRED  # the test `add_seed_tests` chose, not chosen again here
    if seeds is not None:
        print(f"  seeds: {seeds['note']}" if seeds.get("note") else
              f"  seeds: A {_seed_list(seeds['a'])}, B {_seed_list(seeds['b'])}; each metric's 'seeds' line: the "
              f"advantage of the seed means, {int(seeds['level'] * 100)}% "
              f"{'paired t (the same seeds)' if seeds['test'] == SEED_TEST_PAIRED else 'Welch t'} interval, and whether it exceeds "
              f"the spread between seeds")
    for name, m in res["metrics"].items():
        if m["status"] != "ok":
            print(f"  {name:<6} skipped: {m['note']}")
            continue
        ta, tb, td = _abd(m["a"], m["b"], m["advantage"], m["higher_is_better"])
        line = f"  {name:<6} A {ta}  B {tb}  advantage {td}  "
        if m["bootstrap_interval"] is None:
            line += f"interval: {m.get('interval_note') or 'none'}"
            print(line)
            _print_seeds(m)
            continue
        lo, hi = m["bootstrap_interval"]
        line += f"{int(m['level'] * 100)}% [{_fmt(lo)}, {_fmt(hi)}]  P(A better, resampling) {_fmt(m['p_a_better_bootstrap'])}"
        bz = m["bayes"]
        if bz.get("fitted"):
            line += (f"  Student-t: P(mu > 0) {bz['p_a_better']:.3f}  HDI95 [{_fmt(bz['hdi'][0])}, "
                     f"{_fmt(bz['hdi'][1])}]")
            for w in bz.get("warnings", []):
                print(f"skyeyes-bench: warning: {name}: {w}", file=sys.stderr)
        elif bz.get("hdi") is not None:
            line += f"  Student-t: P(mu > 0) {_fmt(bz['p_a_better'])}  ({bz['note']})"
        elif bz.get("note"):
            line += f"  ({bz['note']})"
        print(line)
        _print_seeds(m)
    if any(m.get("bayes", {}).get("fitted") for m in res["metrics"].values()):
        print(f"Student-t mu: the {BAYES_NOTE.format(unit=unit)}")
    return 0
