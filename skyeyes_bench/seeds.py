"""Several seeds of one method (`reproduce --seeds N`): the `seeds` block of a results file, its
check when the file is read, and `compare`'s seed test.

The board's intervals resample scenes: they say how much a value depends on which scenes were
drawn, not on how a network happened to train. A run of N seeds keeps each seed's headline value
per metric; two such runs are compared by a t test of the seed means that says whether their
difference exceeds the spread between seeds: paired by seed when both ran the same seeds (the
difference within each seed, n - 1 degrees of freedom: an ablation that shares a stage seed by
seed, as `skyeyes` and `skyeyes-no-vcm` share the ACM, holds that stage's randomness fixed), else
Welch's (unequal variances, the Welch-Satterthwaite degrees of freedom). Pure functions on results
documents, and `assemble`, which writes a folder's block: `reproduce --seeds` calls it after its runs, and
`skyeyes-bench seeds DIR` where the seeds ran apart (other machines, Slurm array tasks, a GPU) and
each was scored by `evaluate --out DIR/seed-<s>/results.json`.

Block (`results.json["seeds"]`):

```
{"seeds": [0, 1, 2], "results": ["seed-0/results.json", ...],   # beside this file
 "metrics": {name: {"values": [v_0, v_1, v_2], "mean", "sd", "min", "max"}},
 "hardware": ["AMD EPYC (2 cores)", ...]}                       # only where the seeds' machines differ
```
"""

from __future__ import annotations

import math
import re
import statistics
from pathlib import Path

import numpy as np

from . import fields
from .stats import advantage, higher_is_better

#: What the seed test reports (in compare's JSON beside its numbers): Welch's where A and B ran
#: different seeds, paired where they ran the same ones.
_SEED_TEST_END = ("; 'exceeds the seed spread' when the interval excludes 0. It describes how the networks "
                  "happened to train, not which scenes were drawn (the resampling interval above)")
SEED_TEST = ("difference of the seed means of each metric's headline value (advantage of A: > 0 means A is better), "
             "its standard error sqrt(sd_A^2/n_A + sd_B^2/n_B) and a Welch t interval (Welch-Satterthwaite degrees "
             "of freedom)" + _SEED_TEST_END)
SEED_TEST_PAIRED = ("A and B ran the same seeds: the advantage of A within each seed (> 0 means A is better), their "
                    "mean (the difference of the seed means), its standard error sd_d/sqrt(n) and a paired t "
                    "interval (n - 1 degrees of freedom)" + _SEED_TEST_END)
EXCEEDS, WITHIN = "exceeds the seed spread", "within the seed spread"


def spread(values: list[float]) -> dict:
    """{"values", "mean", "sd" (sample sd, ddof=1), "min", "max"} of one metric's per-seed values
    [N >= 2]. A non-finite value (PSNR +inf of an exact seed) leaves no spread: sd null, and the
    mean is the infinity (null if undefined)."""
    assert len(values) >= 2, values
    v = [float(x) for x in values]
    if all(map(math.isfinite, v)):
        mean, sd = statistics.fmean(v), statistics.stdev(v)
    else:
        mean, sd = float(np.mean(v)), None
        mean = None if math.isnan(mean) else mean
    return {"values": v, "mean": mean, "sd": sd, "min": min(v), "max": max(v)}


def seeds_block(seeds: list[int], results: list[str], docs: list[dict]) -> dict:
    """The `seeds` block of N >= 2 runs: `seeds` [N], `results` [N] (their results files, relative
    to the file the block goes into), `docs` [N] (their results); a metric enters when it has
    status ok in every seed, with its headline `value` from each."""
    assert len(seeds) == len(results) == len(docs) >= 2, (seeds, results)
    names = [n for n in docs[0]["metrics"] if all(d["metrics"].get(n, {}).get("status") == "ok" for d in docs)]
    block = {"seeds": list(seeds), "results": list(results),
             "metrics": {n: spread([d["metrics"][n]["value"] for d in docs]) for n in names}}
    from .leaderboard.tables import format_hardware  # the board's Hardware column, word for word

    machines = [format_hardware((d.get("submission") or {}).get("hardware")) or "unknown" for d in docs]
    if len(set(machines)) > 1:  # seeds run apart on other machines: said, since the row shows the first one's
        block["hardware"] = machines
    return block


def format_spread(block: dict, method: str | None = None) -> str:
    """The per-seed spread of a `seeds` block, one line per metric, for a terminal."""
    def g(v):
        return "n/a" if v is None else f"{v:.4g}"

    seeds = ", ".join(map(str, block["seeds"]))
    lines = [f"seeds {seeds}{f' of {method}' if method else ''}: each metric's value over the "
             f"{len(block['seeds'])} seeds (mean, sample sd, min..max; the intervals above resample scenes, "
             f"this is how the training happened to go)"]
    for name, m in block["metrics"].items():
        lines.append(f"  {name:<8} mean {g(m['mean'])}  sd {g(m['sd'])}  {g(m['min'])}..{g(m['max'])}  "
                     f"[{', '.join(map(g, m['values']))}]")
    if block.get("hardware"):
        ran = ", ".join(f"seed {s} on {h}" for s, h in zip(block["seeds"], block["hardware"]))
        lines.append(f"note: the seeds ran on different machines ({ran}); the spread includes the drift between "
                     f"them, and a board row shows seed {block['seeds'][0]}'s hardware")
    return "\n".join(lines)


def check_block(where: str, block) -> None:
    """Raise a one-line UserError at the first field of a results file's `seeds` block (`where`:
    the file) that this version cannot use."""
    fields.conform(where, block, {"seeds": [int], "results": [str], "metrics": {str: {"values": [fields.Number]}}},
                   "seeds")
    n = len(block["seeds"])
    if n < 2:
        fields.fail(f"{where}: field 'seeds.seeds'", f"expected 2 or more seeds, got {n}")
    if len(set(block["seeds"])) != n:
        fields.fail(f"{where}: field 'seeds.seeds'", f"expected distinct seeds, got {fields.short(block['seeds'])}")
    if len(block["results"]) != n:
        fields.fail(f"{where}: field 'seeds.results'", f"expected {n} results files (one per seed), got "
                    f"{len(block['results'])}")
    if "hardware" in block:
        fields.conform(where, block["hardware"], [str], "seeds.hardware")
        if len(block["hardware"]) != n:
            fields.fail(f"{where}: field 'seeds.hardware'", f"expected {n} machines (one per seed), got "
                        f"{len(block['hardware'])}")
    for i, rel in enumerate(block["results"]):  # a path a reader may open: it stays beside the file
        fields.rel_path(f"{where}: field 'seeds.results[{i}]'", rel, "a seed's results file, relative to this one")
    for name, m in block["metrics"].items():
        shown = name if name.isprintable() and len(name) <= 40 else fields.short(name, 40)  # one line
        at = f"{where}: field 'seeds.metrics.{shown}"
        if len(m["values"]) != n:
            fields.fail(at + ".values'", f"expected {n} values (one per seed), got {len(m['values'])}")
        for key in ("mean", "sd", "min", "max"):
            fields.conform(where, m.get(key), fields.Optional(fields.Number), f"seeds.metrics.{shown}.{key}")
        for j, v in enumerate(m["values"]):
            if isinstance(v, float) and math.isnan(v):
                fields.fail(at + f".values[{j}]'", "expected a number, got NaN")


def seed_test(va: list[float], vb: list[float], metric: str, level: float, paired: bool = False) -> dict:
    """A t test on per-seed values va [n_A], vb [n_B] (n >= 2 each) of `metric`: the advantage of
    A's seed mean (> 0: A better, `stats.advantage`), its standard error, degrees of freedom, the
    `level` interval and the verdict. Welch's (`test` "welch"), or with `paired` (va[s] and vb[s]
    of the same seed s, n_A = n_B) the one-sample t of the per-seed advantages (`test` "paired",
    their values in `differences`)."""
    from scipy.stats import t as student_t

    a, b = spread(va), spread(vb)
    out = {"status": "ok", "test": "paired" if paired else "welch", "n_a": len(va), "n_b": len(vb),
           "a_mean": a["mean"], "b_mean": b["mean"], "a_sd": a["sd"], "b_sd": b["sd"], "level": level}
    if a["sd"] is None or b["sd"] is None:
        return {**out, "status": "skipped", "note": "a seed's value is infinite: no seed spread"}
    if paired:  # the mean of the per-seed advantages (the same number as the advantage of the means)
        assert len(va) == len(vb), (va, vb)
        d = advantage(np.asarray(va, float), np.asarray(vb, float), metric)
        adv, sd_d = float(np.mean(d)), statistics.stdev(d.tolist())
        se, df = sd_d / math.sqrt(len(d)), float(len(d) - 1)
        out["differences"] = d.tolist()
    else:
        adv = float(advantage(np.array([a["mean"]]), np.array([b["mean"]]), metric)[0])
        va_n, vb_n = a["sd"] ** 2 / len(va), b["sd"] ** 2 / len(vb)  # squared standard errors of the two means
        se = math.sqrt(va_n + vb_n)
        den = va_n ** 2 / (len(va) - 1) + vb_n ** 2 / (len(vb) - 1)
        df = se ** 4 / den if den > 0 else float(len(va) + len(vb) - 2)  # den underflows only for sd ~ 1e-160
    out.update(advantage=adv, se=se, higher_is_better=higher_is_better(metric))
    if se == 0:  # the difference is exact: every seed alike in A and in B (paired: every seed's difference alike)
        out.update(df=None, interval=[adv, adv], verdict=EXCEEDS if adv != 0 else WITHIN,
                   note=("every seed's difference the same" if paired else "no spread between the seeds of "
                         "either run") + ": the interval is the difference itself")
        return out
    half = float(student_t.ppf(0.5 + level / 2, df)) * se
    lo, hi = adv - half, adv + half
    out.update(df=df, interval=[lo, hi], verdict=EXCEEDS if lo > 0 or hi < 0 else WITHIN)
    return out


def add_seed_tests(out: dict, a: dict, b: dict, names: tuple[str, str], level: float) -> None:
    """Into the comparison `out` (`comparison.compare_results`) of results `a` and `b`: when both
    carry a `seeds` block, `out["seeds"]` (both runs' seeds, the test) and per compared metric
    `out["metrics"][m]["seeds"]` (`seed_test`: paired when both ran the same seeds in the same
    order, else Welch's); when only one does, `out["seeds"]` says so in
    its `note`; when neither, nothing."""
    blocks = [d.get("seeds") for d in (a, b)]
    if blocks == [None, None]:
        return
    for name, blk in zip(names, blocks):
        if blk is not None:
            check_block(name, blk)
    paired = None not in blocks and blocks[0]["seeds"] == blocks[1]["seeds"]
    out["seeds"] = {"a": blocks[0] and blocks[0]["seeds"], "b": blocks[1] and blocks[1]["seeds"],
                    "test": SEED_TEST_PAIRED if paired else SEED_TEST, "level": level}
    if None in blocks:
        has, lacks = (("A", "B"), names) if blocks[0] is not None else (("B", "A"), names[::-1])
        n = len((blocks[0] or blocks[1])["seeds"])
        out["seeds"]["note"] = (f"only {has[0]} ({lacks[0]}) ran several seeds ({n}); {has[1]} is one run: no "
                                f"seed test")
        return
    ma, mb = blocks[0]["metrics"], blocks[1]["metrics"]
    for name, r in out["metrics"].items():
        if r.get("status") != "ok":
            continue
        if name not in ma or name not in mb:
            r["seeds"] = {"status": "skipped", "note": f"{name} not scored in every seed of "
                          f"{'A' if name not in ma else 'B'}"}
            continue
        r["seeds"] = seed_test(ma[name]["values"], mb[name]["values"], name, level, paired=paired)


#: A seed's folder inside a folder of several seeds.
SEED_DIR = re.compile(r"seed-(\d+)")


def seed_dirs(out: Path) -> list[int]:
    """The seeds s of `out`'s seed-<s>/ folders that hold a results.json, in order."""
    found = [int(m.group(1)) for d in Path(out).iterdir() if (m := SEED_DIR.fullmatch(d.name))
             and (d / "results.json").is_file()] if Path(out).is_dir() else []
    return sorted(found)


def check_seeds_out(out: Path, force: bool) -> None:
    """Refuse an `out` of several seeds that holds a single run (its config.json: the seeds go into
    seed-<s>/ folders beside one results.json), or a results.json other than an earlier one of
    several seeds (that is replaced: it is made from the seed folders) unless `force`."""
    from . import inputfiles, outputfiles
    from .errors import UserError
    from .results import FEATURES_OUTPUT, RESULTS_OUTPUT, features_path

    if (out / "config.json").is_file():
        raise UserError(f"{out}: holds a single run (its config.json); a run of several seeds writes seed-<s>/ "
                        "folders beside one results.json: choose another --out")
    res = out / "results.json"
    try:
        ours = isinstance(inputfiles.read_json(res, allow_nan=True).get("seeds"), dict)
    except (UserError, AttributeError):  # absent, unreadable or not an object: `check_output` says
        ours = False
    outputfiles.check_output(res, force=force or ours, sidecars=[features_path(res)], kind=RESULTS_OUTPUT,
                             sidecar_kind=FEATURES_OUTPUT)


def _identity(doc: dict) -> dict:
    """What every seed of one row shares: method, protocol, dataset and split."""
    sub, data = doc.get("submission") or {}, doc.get("dataset") or {}
    return {"submission.method": sub.get("method"), "protocol.ref": (doc.get("protocol") or {}).get("ref"),
            "dataset.name": data.get("name"), "dataset.split": data.get("split")}


def assemble(out, seeds: list[int] | None = None, *, force: bool = False) -> dict:
    """Write `out`/results.json (and its features sidecar): seed `seeds[0]`'s results (frames,
    replicates and sidecar intact, so `compare` pairs it like any results file) with the `seeds`
    block of `out`/seed-<s>/results.json for each s of `seeds` (None: every seed folder there, at
    least 2). The seeds must be one method's on one protocol, dataset and split; a results file
    that is not, or is missing, is a one-line UserError naming it. Returns the document."""
    from .errors import UserError
    from .results import read_results, write_results

    out = Path(out)
    ss = seed_dirs(out) if seeds is None else list(seeds)
    if len(ss) < 2:
        raise UserError(f"{out}: {len(ss)} seed-<s>/results.json found, expected 2 or more (each seed's run scored "
                        f"into {out}/seed-<s>/results.json)")
    docs = []
    for i, s in enumerate(ss):
        path = out / f"seed-{s}" / "results.json"
        if not path.is_file():
            raise UserError(f"{path}: missing (seed {s}'s results)")
        docs.append((path, *read_results(path, features=i == 0)))
    want = _identity(docs[0][1])
    for path, d, _ in docs[1:]:
        got = _identity(d)
        for k in want:
            if got[k] != want[k]:
                raise UserError(f"{path}: field '{k}' is {fields.short(got[k])}, expected {fields.short(want[k])} "
                                f"(seed {ss[0]}'s): the seeds of one row share method, protocol, dataset and split")
    (_, doc, features), *_ = docs
    doc["seeds"] = seeds_block(ss, [f"seed-{s}/results.json" for s in ss], [d for _, d, _ in docs])
    check_seeds_out(out, force)  # at the point of writing: another run may have written it since its runs began
    write_results(out / "results.json", doc, features)
    return doc
