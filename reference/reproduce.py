"""`skyeyes-bench reproduce`: data -> fit -> render -> submission -> evaluate -> results.json.

Output folder (`--out`, default `outputs/<method>-<preset>/`):

```
config.json            resolved config (preset + overrides), cache key, dataset and code hashes
reproduce.log          the run's log (SfM outcome, fallbacks, timings)
work/<key>/            stage cache, key = sha256(method, config, seed, dataset manifest, code)
    train/             what the method learned on the train split (its checkpoint + fit.json)
    scenes/<scene>/    fitted model checkpoint (model.pt, written atomically) + fit.json
    renders/<scene>/ground/NNNNNN.png, renders/timings.json   rendered frames, reused on resume
submission/            the submission (SubmissionWriter)
results.json           evaluate(...) of the submission (a finished run asked again reuses it: `scored`)
```

With several seeds (`run_seeds`, `reproduce --seeds N`) each seed s is such a folder,
`seed-<s>/`, and `results.json` beside them is the first seed's results with a `seeds` block
(every seed's headline values and their spread; `skyeyes_bench.seeds`).

An --out belongs to one run, the one its config.json records: the same run (same cache key)
resumes there; any other run is refused (`check_out`) unless --force, which replaces its outputs.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import resource
import shutil
import sys
import time
from pathlib import Path

from reference.method import cache_key, code_sha, json_sha
from skyeyes_bench import imagefiles, inputfiles, outputfiles
from skyeyes_bench.errors import UserError

log = logging.getLogger("reference.reproduce")


def dataset_sha(root: Path, ds) -> str:
    """sha256 of the dataset manifest (dataset.json and every scene.json)."""
    h = hashlib.sha256(inputfiles.sha256_file(root / "dataset.json").encode())
    for name in sorted(ds.scenes):
        h.update(inputfiles.sha256_file(root / name / "scene.json").encode())
    return h.hexdigest()


def check_out(out: Path, mine: dict, *, force: bool) -> None:
    """Refuse an --out that holds another run's outputs, unless `force`.

    The run in `out` is the one its config.json records. The same run (same cache key) resumes
    there without --force; a different one (or outputs with no config.json) would be silently
    replaced, so that is a one-line UserError. `mine` holds what is known of this run so far:
    before the dataset is opened, method, method_version, seed and the resolved config (a cheap
    early check); after, also the cache key, which decides.
    """
    if force or not out.is_dir():
        return
    cfg = out / "config.json"
    if cfg.is_file():
        try:
            theirs = inputfiles.read_json(cfg, allow_nan=True)
        except UserError:
            theirs = {}
        if "cache_key" in mine and theirs.get("cache_key") == mine["cache_key"]:
            return
        why = _difference(theirs, mine)
        if why is None:
            return  # the early check: nothing known so far differs
    elif any((out / name).exists() for name in ("results.json", "submission", "work")):
        why = "outputs without a config.json"
    else:
        return
    raise UserError(f"{out}: holds the outputs of another run ({why}); pass --force to replace them, "
                    "or choose another --out")


def _difference(theirs: dict, mine: dict) -> str | None:
    """The first way the recorded run `theirs` differs from `mine`, in words (None: none known)."""
    for k in ("method", "method_version", "seed"):
        if theirs.get(k) != mine[k]:
            return f"{k} {theirs.get(k)!r} there, {mine[k]!r} here"
    old, new = theirs.get("config") or {}, json.loads(json.dumps(mine["config"]))  # tuples as JSON lists
    if old != new:
        keys = [*new, *(k for k in old if k not in new)]
        diff = [f"{k}={old.get(k, '<unset>')!r} there, {new.get(k, '<unset>')!r} here" for k in keys
                if old.get(k) != new.get(k)]
        return "config " + "; ".join(diff[:3]) + (f"; {len(diff) - 3} more" if len(diff) > 3 else "")
    if "cache_key" not in mine:
        return None
    if (theirs.get("dataset") or {}).get("manifest_sha256") != mine["dataset"]["manifest_sha256"]:
        return f"dataset {(theirs.get('dataset') or {}).get('root')!r} there, {mine['dataset']['root']!r} here"
    if theirs.get("code_sha256") != mine["code_sha256"]:
        return "made by other code of the method"
    return f"cache key {theirs.get('cache_key')!r} there, {mine['cache_key']!r} here"


def _main_process() -> bool:
    """False in the non-main processes of an `accelerate launch` (torch.distributed's RANK)."""
    return int(os.environ.get("RANK", "0")) == 0


def peak_rss_mb() -> float:
    """Peak resident memory of the run (MB): this process's, plus, when scene fits ran in worker
    processes, that many times the largest worker's (an upper bound: they ran side by side)."""
    from reference.parallel import most_workers

    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # Linux: KiB
    workers = most_workers() * resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return (own + workers) / 1024.0


def _peak_gpu_note() -> str:
    """", peak GPU memory N MB" of this process where it used CUDA (worker processes, such as
    the lanes of a prior, hold their own), else ""."""
    torch = sys.modules.get("torch")
    if torch is None or not torch.cuda.is_initialized():
        return ""
    return f", peak GPU memory {torch.cuda.max_memory_allocated() / 2**20:.0f} MB in this process"


def _setup_log(out: Path, *, fresh: bool = False) -> tuple[logging.Handler, ...]:
    out.mkdir(parents=True, exist_ok=True)
    fh = logging.FileHandler(out / "reproduce.log", mode="w" if fresh else "a")
    fh.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    sh = logging.StreamHandler(sys.stderr)
    sh.setFormatter(logging.Formatter("%(levelname)s: %(message)s"))
    root = logging.getLogger("reference")
    root.setLevel(logging.INFO)
    root.addHandler(fh)
    root.addHandler(sh)
    return fh, sh


@contextlib.contextmanager
def _on_ray(address: str):
    """Ray for the run (`ray_exec.session`), and the scene fits as its tasks (`parallel.on_ray`)."""
    from reference.parallel import on_ray
    from skyeyes_bench import ray_exec

    with ray_exec.session(address or None), on_ray():
        yield


def scored(out: Path, ds) -> dict | None:
    """`out`/results.json when it is the score of this run's finished submission, else None.

    Called once `check_out` has found `out`'s config.json to be this run's (the same cache key:
    method, config, seed, dataset and code), so a results.json there scored this run unless the
    submission's frames are not the ones it scored (written again since and rendered anew, or
    any missing: the hashes of the frames dataset `ds` expects, against the results'), or the
    protocol or the tool changed (their sha256 and version there differ from here's).
    So is a metric reported unavailable there for want of weights that are here now. Such a file
    is reused rather than scored again: a run of several seeds resumed after its first seed does
    not spend the scoring time again."""
    from skyeyes_bench import __version__
    from skyeyes_bench.protocol import load_protocol
    from skyeyes_bench.results import read_results
    from skyeyes_bench.scoring.run import frame_hashes, frames_digest

    res_path = out / "results.json"
    if not res_path.is_file():
        return None
    try:
        res, _ = read_results(res_path)
        protocol = load_protocol(res["protocol"]["ref"])
        theirs = res["submission"]["frames_sha256"]
    except (UserError, KeyError, TypeError):
        return None  # unreadable or of another format: score again
    same = (protocol.sha256 == res["protocol"]["sha256"]
            and (res.get("tool") or {}).get("version") == __version__
            and res.get("shard") is None
            and not _computable_now(protocol, res)
            and frames_digest(frame_hashes(out / "submission", ds)) == theirs)
    return res if same else None


def _computable_now(protocol, res: dict) -> bool:
    """Whether a metric `res` reports unavailable needs an extractor whose weights are here now
    (fetched since): scoring again gives it."""
    from skyeyes_bench.scoring.inputs import missing_weights

    gone = [m.name for m in protocol.metrics
            if m.extractor and (res["metrics"].get(m.name) or {}).get("status") == "unavailable"]
    return bool(gone) and not set(gone) <= set(missing_weights(protocol))


def _score(sub_dir: Path, root: Path, out: Path, ray: str | None, progress: bool) -> dict:
    """`evaluate` of the submission into `out` (replaced); with `ray`, as shards on the running Ray."""
    from skyeyes_bench.batch import Job, evaluate_batch
    from skyeyes_bench.evaluate import evaluate

    if ray is None:
        return evaluate(sub_dir, data=root, out=out, force=True, progress=progress)
    got = evaluate_batch([Job(sub_dir, out, data=str(root))], ray=ray, force=True, progress=progress)[0]
    if got.error is not None:
        raise UserError(got.error) if got.exit_code == 2 else RuntimeError(got.error)
    return got.results


def run(method: str, preset: str = "smoke", data=None, out=None, seed: int = 0, overrides: list[str] | None = None,
        force: bool = False, progress: bool = True, device: str | None = None,
        pretrained: str | None = None, jobs: int | None = None, ray: str | None = None, split: str = "test") -> dict:
    """The whole pipeline; returns the results dict (the module docstring lists the files). jobs:
    scene fits at once in worker processes (`reference.parallel`; None: every core for the CPU geometry
    methods, else 1). ray: None, or scene fits and scoring as Ray tasks at this address ("": a local
    Ray; `_on_ray`). Neither changes the results. split: "test", or "val": the run fits, renders and
    scores the validation split (`splits.scored_view`; without `data`, the preset's validation data)."""
    from reference.parallel import default_jobs
    from skyeyes_bench.evaluate import format_summary
    from skyeyes_bench.splits import check_split

    _check_options(jobs, ray)
    check_split(split)
    out = Path(out) if out is not None else Path("outputs") / f"{method}-{preset}{'-val' if split == 'val' else ''}"
    cls, config, overrides = _early_check(method, preset, overrides, device, pretrained, seed, out, force)
    config_d = dataclasses.asdict(config)
    root, ds, key, record = _run_record(method, preset, cls, config_d, seed, overrides, data, split, progress)
    check_out(out, record, force=force)  # before anything is written to --out
    # --out is apart from what the run reads; every write below checks again (`outputfiles.reading`)
    inputs = (root, config_d.get("pretrained"))
    outputfiles.check_apart(out, *inputs, desc="an input of this run (--data, --pretrained)")
    held = contextlib.ExitStack()
    if ray is not None:  # before any output: Ray missing or unreachable is one line
        held.enter_context(_on_ray(ray))
    handlers = _setup_log(out, fresh=force)
    held.enter_context(outputfiles.reading(*inputs))
    try:
        work = out / "work" / key
        if force and work.exists():
            shutil.rmtree(work)
        outputfiles.write_json(out / "config.json", record)
        log.info("reproduce %s (preset %s) on %s; stage cache %s", method, preset, ds.name, work)
        res = None if force else scored(out, ds)
        if res is not None:  # this run finished and was scored: nothing left to do
            log.info("%s already scores this run's submission (the same cache key, frames, protocol and tool "
                     "version): reused; --force runs it again", out / "results.json")
            print(f"{format_summary(res)}\nresults: {out / 'results.json'}")
            return res if _main_process() else {}
        m = cls(config, work / "method", seed=seed, progress=progress)
        m.jobs = default_jobs(m) if jobs is None else jobs
        log.info("scene fits: %s", "Ray tasks (--ray)" if ray is not None else f"{m.jobs} worker process(es) (--jobs)")
        fit_s = _fit(m, ds, progress)  # 2. Fit: train split, then each test scene (resumable)
        if fit_s is None:
            return {}
        scenes = ds.split("test")
        # 3. Render every test sequence; frames already in the cache are reused.
        renders = work / "renders"
        timings, cached_renders_s = _render(m, scenes, renders, progress)
        # Work taken from caches (diffusion stages, priors, resumed fits, rendered frames) is
        # reported at its original cost, and how much of the total that is: a run's time is what
        # producing its result cost, not how long this invocation happened to take.
        cached_s = m.cached_s + cached_renders_s
        # 4. Submission from the render cache.
        per_frame = [timings[f"{sc.name}/{f.file}"] for sc in scenes for s in sc.sequences.values() for f in s]
        sub_dir = out / "submission"
        # what the board says of the row: the method's kind and every component it ran
        sub_config = {"preset": preset, "seed": seed, "cache_key": key, **config_d, "kind": m.kind,
                      "components": m.components()}
        _write_submission(sub_dir, ds, scenes, renders, method, cls.version, sub_config,
                          {"fit_s": fit_s, "render_s": float(sum(per_frame)), "per_frame_render_s": per_frame,
                           "cached_s": cached_s})
        log.info("submission written: %s (fit %.1f s, render %.1f s, peak RSS %.0f MB%s)", sub_dir, fit_s,
                 sum(per_frame), peak_rss_mb(), _peak_gpu_note())
        # 5. Evaluate.
        res = _score(sub_dir, root, out / "results.json", ray, progress)
        print(f"{format_summary(res)}\nresults: {out / 'results.json'}")
        _copy_figure(work / "method" / "figure.png", out / "figure.png")
        return res
    finally:
        held.close()
        lg = logging.getLogger("reference")
        for h in handlers:
            lg.removeHandler(h)
            h.close()


def _run_record(method: str, preset: str, cls, config_d: dict, seed: int, overrides: list[str], data, split: str,
                progress: bool):
    """The run's dataset (generated when `data` is None; with split "val" its validation scenes as
    the test split), its cache key and config.json's record: (root, dataset, key, record)."""
    from skyeyes_bench.data.layout import open_dataset
    from skyeyes_bench.splits import scored_view

    if data is None:  # 1. Data
        from skyeyes_bench.data.synthtown import ensure_dataset

        data = ensure_dataset(preset, progress=progress, split=split)
    root = Path(data)
    ds = open_dataset(root)
    if split == "val":  # the validation scenes as its test split (`scored_view`); the protocol says where they are
        from skyeyes_bench.protocol import current_for_data, load_protocol

        ds = scored_view(ds, split, load_protocol(current_for_data(ds.protocol)))
    dsha, csha = dataset_sha(root, ds), code_sha(cls)
    if split != "test":  # a run on another split of the same dataset is another run
        dsha = json_sha([dsha, split])
    key = cache_key(method, cls.version, config_d, seed, dsha, csha)
    record = {"method": method, "method_version": cls.version, "preset": preset, "overrides": overrides, "seed": seed,
              "config": config_d, "cache_key": key, "dataset": {"root": str(root), "name": ds.name, "split": split,
              "manifest_sha256": dsha}, "code_sha256": csha, "repeat": f"skyeyes-bench reproduce --method {method} "
              f"--preset {preset} --seed {seed} --data {root} " + (f"--split {split} " if split != "test" else "")
              + " ".join(f"--set {o}" for o in overrides)}
    return root, ds, key, record


def _early_check(method: str, preset: str, overrides: list[str] | None, device: str | None, pretrained: str | None,
                 seed: int, out: Path, force: bool):
    """The method's class, its resolved config and overrides, once `check_out` has found nothing
    known so far that makes `out` another run's (before the dataset is generated)."""
    from reference.methods import get_method_class

    cls = get_method_class(method)
    config, overrides = cls.configure(preset, overrides or [], device=device, pretrained=pretrained)
    check_out(out, {"method": method, "method_version": cls.version, "seed": seed,
                    "config": dataclasses.asdict(config)}, force=force)
    return cls, config, overrides


def run_seeds(method: str, preset: str = "smoke", seeds: int = 2, *, seed: int = 0, data=None, out=None,
              overrides: list[str] | None = None, force: bool = False, progress: bool = True,
              device: str | None = None, pretrained: str | None = None, jobs: int | None = None,
              ray: str | None = None, split: str = "test") -> dict:
    """`run` once per seed `seed`, `seed` + 1, ..., `seed` + `seeds` - 1, seed s into `out/seed-<s>/`
    (each a complete run that resumes like any other), then `out/results.json` and its features
    sidecar: the first seed's results (frames, replicates and sidecar intact, so `compare` pairs it
    like any results file) with a `seeds` block (`skyeyes_bench.seeds.seeds_block`): every seed's
    headline value per metric and their spread. Returns that document ({} in a non-main process of
    `accelerate launch`). The other arguments are `run`'s; `out` defaults to
    `outputs/<method>-<preset>[-val]-seeds`."""
    from skyeyes_bench.seeds import assemble, check_seeds_out, format_spread

    if seeds < 2:
        raise UserError(f"--seeds {seeds}: expected 2 or more seeds (a single run takes --seed)")
    _check_options(jobs, ray)
    if out is None:
        out = Path("outputs") / f"{method}-{preset}{'-val' if split == 'val' else ''}-seeds"
    out = Path(out)
    ss = list(range(seed, seed + seeds))
    outputfiles.check_apart(out, data, pretrained, desc="an input of this run (--data, --pretrained)")
    check_seeds_out(out, force)
    for s in ss:  # every seed's folder before any work: another run's is refused now, not after hours
        _early_check(method, preset, overrides, device, pretrained, s, out / f"seed-{s}", force)
    for s in ss:  # 1. each seed: the single-seed run, its own folder, resumed like any other
        if not run(method, preset, data=data, out=out / f"seed-{s}", seed=s, overrides=overrides, force=force,
                   progress=progress, device=device, pretrained=pretrained, jobs=jobs, ray=ray, split=split):
            return {}  # `accelerate launch`: the main process alone scores and aggregates
    # 2. the first seed's results, its sidecar beside them, and every seed's headline values
    with outputfiles.reading(data, pretrained):
        doc = assemble(out, ss, force=force)
    print(f"{format_spread(doc['seeds'], method)}\nresults: {out / 'results.json'} (seed {ss[0]}'s results with the "
          f"seeds block; each seed's in {out}/seed-<s>/)")
    return doc


def _render(m, scenes: list, renders: Path, progress: bool) -> tuple[dict, float]:
    """Every test sequence of `scenes` rendered by method `m` into `renders/<scene>/<file>`, one
    atomic write a frame; a sequence whose frames and timings are all there already is reused.
    Returns the per-frame seconds ({"scene/file": s}, also in `renders/timings.json`, written
    after each sequence) and the seconds of the reused frames (their original cost)."""
    from tqdm import tqdm

    tfile = renders / "timings.json"
    timings = inputfiles.read_json(tfile, allow_nan=True) if tfile.is_file() else {}
    total = sum(len(s) for sc in scenes for s in sc.sequences.values())
    cached_s = 0.0
    with tqdm(total=total, desc="render", disable=None if progress else True, leave=False) as bar:
        for scene in scenes:
            for seq in scene.sequences.values():
                paths = [renders / scene.name / f.file for f in seq]
                if all(p.is_file() for p in paths) and all(f"{scene.name}/{f.file}" in timings for f in seq):
                    bar.update(len(paths))
                    cached_s += sum(timings[f"{scene.name}/{f.file}"] for f in seq)
                    continue
                t_prev = time.perf_counter()
                for frame, img, p in zip(seq, m.render_sequence(scene, seq), paths):
                    imagefiles.write_image(p, img)  # atomic per frame
                    now = time.perf_counter()
                    timings[f"{scene.name}/{frame.file}"] = now - t_prev
                    t_prev = now
                    bar.update(1)
                outputfiles.write_json(tfile, timings)
    return timings, cached_s


def _check_options(jobs: int | None, ray: str | None) -> None:
    """--jobs and --ray, before any work: a one-line UserError for a bad pair, or for --ray
    without Ray installed (with the command that installs it)."""
    if jobs is not None and jobs < 1:
        raise UserError(f"--jobs {jobs}: expected a number of worker processes >= 1")
    if ray is not None and jobs is not None:
        raise UserError("--jobs with --ray: Ray places the scene fits by the cluster's CPUs; --jobs is for local "
                        "worker processes (give one of them)")
    if ray is not None:
        from skyeyes_bench.ray_exec import require_ray

        require_ray()


def _copy_figure(fig: Path, dest: Path) -> None:
    """A method's figure (Skyeyes: aerial, prior, generated, ground truth) beside the results, or
    no figure there when this run made none (another run's, replaced with --force)."""
    if fig.is_file():
        with outputfiles.atomic_path(dest) as tmp:
            shutil.copyfile(fig, tmp)
        print(f"figure: {dest}")
    elif dest.is_file():
        dest.unlink()


def _write_submission(sub_dir: Path, ds, scenes: list, renders: Path, method: str, version: str, config: dict,
                      timings: dict) -> None:
    """The submission folder from the render cache (`renders/<scene>/<file>`), with the run's
    timings, peak memory and hardware."""
    from skyeyes_bench.submission import SubmissionWriter

    with SubmissionWriter(sub_dir, dataset=ds, method=method, method_version=version, config=config,
                          overwrite=True) as w:
        for sc in scenes:
            for s in sc.sequences.values():
                for f in s:
                    w.add(sc.name, f, imagefiles.read_image(renders / sc.name / f.file))
        w.finish(timings=timings, peak_memory_mb=peak_rss_mb(), hardware=None)


def _fit(m, ds, progress: bool) -> float | None:
    """`m.fit_train` on the train split, then `m.fit_scenes` on the test scenes; the fit's time:
    its wall time plus the original time of what it took from caches (`m.cached_s`). None in a
    process of `accelerate launch` other than the main one, which alone goes on to render."""
    t0 = time.perf_counter()
    m.fit_train(ds)
    if not _main_process():
        # `accelerate launch`: every process trains its share of the batches; the main
        # process alone renders, writes the submission and scores it.
        log.info("process %s: training done; the main process renders and scores", os.environ.get("RANK"))
        return None
    scenes = ds.split("test")
    m.fit_scenes(scenes, progress=progress)
    for scene in scenes:
        stats = m.scene_stats.get(scene.name, {})
        log.info("%s: fitted (%s)", scene.name, ", ".join(f"{k}={stats[k]}" for k in ("gaussians", "final_loss") if k in stats))
    return time.perf_counter() - t0 + m.cached_s
