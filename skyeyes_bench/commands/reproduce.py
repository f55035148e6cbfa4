"""`skyeyes-bench reproduce`: fit a reference method, render the test ground cameras, score."""

from __future__ import annotations

import sys

from ..batch import RAY_HELP


def register(sub) -> None:
    p = sub.add_parser(
        "reproduce", help="fit a reference method, write a submission and score it",
        description="Run a reference method end to end: data (SynthTown by default), fit on each test "
        "scene's aerial views, render its ground cameras, write a submission, evaluate it, print the "
        "summary and leave results.json in --out. Stages are cached by content hash under --out, so an "
        "interrupted run resumes where it stopped: run the same command again (a finished one prints its "
        "results.json, not scored again unless its frames, the protocol or the tool changed). An --out holding another "
        "run's outputs (another method, config, seed, dataset or code: its config.json says) is refused "
        "unless --force.")
    p.add_argument("--method", required=True, help="reference method id (e.g. sugar, gaussians3d, skyeyes)")
    p.add_argument("--preset", default="smoke", help="method preset: smoke | small | paper (default: smoke)")
    p.add_argument("--data", default=None, metavar="DIR",
                   help="dataset folder (default: the SynthTown dataset of the same preset, generated once; with "
                   "--split val its validation data)")
    p.add_argument("--split", choices=("test", "val"), default="test",
                   help="the scenes fitted, rendered and scored: test (default), or val, the validation split where "
                   "settings are chosen (the protocol's val.toml: SynthTown's own validation towns; for CARLA and "
                   "CitySample a part of the train towns, then left out of training); never ranked")
    p.add_argument("--out", default=None, metavar="DIR", help="output folder (default: outputs/<method>-<preset>, "
                   "with --split val outputs/<method>-<preset>-val)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0); with --seeds the first seed")
    p.add_argument("--seeds", type=int, default=None, metavar="N",
                   help="run the method N >= 2 times, with seeds --seed, --seed + 1, ..., each into --out/seed-<s>/ "
                        "(a complete run that resumes like any other), then write --out/results.json: the first "
                        "seed's results with a 'seeds' block of every seed's values and their spread, which "
                        "compare tests against another such file (default --out: outputs/<method>-<preset>-seeds)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override one config field of the preset (repeatable), e.g. --set iterations=200")
    p.add_argument("--device", default=None, metavar="DEV",
                   help="torch device the method runs on, e.g. cpu, cuda, cuda:1 (default: the preset's: cpu, or for "
                        "the diffusion methods CUDA when available). For several GPUs run the diffusion stages "
                        "data-parallel: accelerate launch --multi_gpu --num_processes N -m skyeyes_bench.cli reproduce ...")
    p.add_argument("--pretrained", default=None, metavar="DIR",
                   help="diffusion methods (skyeyes, skyeyes-no-vcm, controlnet, ip2p, gvg): a local Stable Diffusion "
                        "1.5 diffusers folder (unet/, vae/, text_encoder/, tokenizer/, optional controlnet/); its UNet, "
                        "VAE and text encoder replace the from-scratch model, with the paper's ControlNet branch (ip2p, "
                        "gvg: the condition concatenated, conv_in widened) and epsilon objective. Nothing is downloaded.")
    p.add_argument("--jobs", type=int, default=None, metavar="N",
                   help="worker processes fitting scenes (lanes) at once; results are identical for any N, only the "
                        "run time changes (default: every core for the CPU geometry methods and Skyeyes' prior, "
                        "which fit a lane on one thread; else 1)")
    p.add_argument("--ray", nargs="?", const="", metavar="ADDRESS",
                   help=RAY_HELP + ": the test "
                        "lanes of the geometry methods and Skyeyes' prior fit as Ray tasks in place of --jobs's worker "
                        "processes (--out on a shared path too, for the checkpoints), and the submission is scored as "
                        "shards on Ray; the same results")
    p.add_argument("--force", action="store_true",
                   help="discard this run's cached stages and replace the outputs in --out, also another run's "
                        "(without it the same run resumes, another run's --out is refused)")
    p.add_argument("--quiet", action="store_true", help="no progress bars (they are drawn only on a terminal anyway)")
    p.set_defaults(run=run)


def run(args) -> int:
    # The one place skyeyes_bench imports `reference` (the methods), and only when the command runs.
    from reference import reproduce
    from skyeyes_bench.batch import ray_address

    kw = dict(data=args.data, out=args.out, seed=args.seed, overrides=args.overrides, force=args.force,
              progress=not args.quiet and sys.stderr.isatty(), device=args.device, pretrained=args.pretrained,
              jobs=args.jobs, ray=ray_address(args.ray, []), split=args.split)
    if args.seeds is not None:  # several seeds: `run` once per seed, then their spread
        reproduce.run_seeds(args.method, args.preset, args.seeds, **kw)
    else:
        reproduce.run(args.method, args.preset, **kw)
    return 0
