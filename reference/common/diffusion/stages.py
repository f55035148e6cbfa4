"""The training stages of the diffusion family (`pipeline.DiffusionMethod.fit_train`), each
trained, or resumed, into its checkpoint in the stage cache,
`<cache>/reference/diffusion/<stage>-<hash of its key>/train-<steps>.pt`:

1. base: without a pretrained Stable Diffusion, a UNet trained unconditionally on the train
   split's ground-truth frames (it stands in for the pretrained LDM); only for a ControlNet
   branch trained from scratch.
2. ACM: the condition's way in (a ControlNet branch from the UNet, UNet frozen; or the
   concatenated input of a UNet trained whole), trained to denoise ground truth conditioned on
   its condition; the guidance part may drop conditions (`guidance`).
3. VCM: a copy of the frozen ACM gets clip self-attention (`vcm.install_vcm`); its attn1
   projections are fine-tuned on clips with first-frame conditioning.

A stage's key holds everything the stage depends on except its own step count, plus the full
identity (with steps) of the stage it starts from, so `skyeyes`, `skyeyes-no-vcm` and the
baselines share in the cache what they have in common.
"""

from __future__ import annotations

import copy
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from reference.method import json_sha
from skyeyes_bench import outputfiles
from skyeyes_bench.paths import cache_dir

from . import core, train, vcm

if TYPE_CHECKING:
    from reference.method import Method

#: Bumped whenever a change makes old stage checkpoints mean something else (architecture,
#: losses): it is part of every stage cache key. 2: heads sized by `head_dim`. 3: data-parallel
#: batch split, loss weights, VCM in the UNet's down and up blocks only.
STAGE_VERSION = 3


def stage_ckpt(stage: str, key: dict, steps: int) -> Path:
    """`<cache>/reference/diffusion/<stage>-<hash of everything but the step count>/train-<steps>.pt`,
    started from the furthest shorter run of the same stage (`train.stage_checkpoint`)."""
    ident = {"stage": stage, "stage_version": STAGE_VERSION, **key}
    return train.stage_checkpoint(cache_dir() / "reference" / "diffusion" / f"{stage}-{json_sha(ident)[:20]}", steps)


@dataclass
class TrainSet:
    """The train split in model space, one row per ground frame (`frames`: (scene, frame))."""

    frames: list[tuple[Any, Any]]
    z0: torch.Tensor  # [N, C, h, w] what the model diffuses (the frames, or their residual)
    cond: torch.Tensor  # [N, C', h, w] the conditions in model space
    data_hash: str  # of the frames in model space
    cond_hash: str  # of the conditions in model space

    @property
    def n(self) -> int:
        return len(self.frames)

    def sequences(self, scenes: list) -> list[list[int]]:
        """The rows of every ground sequence of `scenes` with at least 2 frames, in order."""
        seqs = [[self.frames.index((s, f)) for f in q.frames] for s in scenes for q in s.sequences.values()]
        return [q for q in seqs if len(q) >= 2]


def train_set(frames: list, frame_images: list, cond_images: list, to_model, cfg: core.CoreConfig,
              device) -> TrainSet:
    """The frames' images and their conditions (float32 [H, W, C] each) in model space on
    `device`; `to_model`: images -> [N, C, res, res] at the model's resolution."""
    x0 = core.encode(to_model(frame_images), cfg, device)
    cc = core.encode_cond(to_model(cond_images), cfg, device)
    z0 = core.to_diffused(x0, cc, cfg)
    return TrainSet(frames, z0, cc, hashlib.sha256(x0.cpu().numpy().tobytes()).hexdigest(),
                    hashlib.sha256(cc.cpu().numpy().tobytes()).hexdigest())


class Stages:
    """The stages of one method's run: each trained (or resumed) by `run`, its summary kept in
    `method.training` and the run's training.json, the seconds of resumed work in
    `method.cached_s`."""

    def __init__(self, method: "Method", accelerator, data: TrainSet):
        self.m, self.acc, self.data = method, accelerator, data
        c = method.config
        self.sched = core.train_scheduler(c.core)
        self.gamma = c.snr_gamma or None
        self.run_kw = dict(accelerator=accelerator, ema_decay=c.ema_decay, micro_batches=c.micro_batches,
                           compile_mode=c.compile)

    def run(self, stage: str, model, params, loss_fn, steps: int, lr: float, key: dict, *,
            anneal_from: int | None = None, entry: str | None = None) -> dict:
        """Train (or resume) one stage into its cache checkpoint; its summary goes to training.json
        under `entry` (default: the stage's name)."""
        m, acc = self.m, self.acc
        ckpt = stage_ckpt(stage, key, steps)
        extra = {} if anneal_from is None else {"anneal_from": anneal_from}
        res = train.train_loop(model, params, loss_fn, steps=steps, lr=lr, seed=m.seed, ckpt=ckpt,
                               ckpt_every=m.config.ckpt_every, progress=m.progress, desc=stage, **self.run_kw, **extra)
        tail = res["losses"][-max(1, steps // 10):]
        summary = {"checkpoint": str(ckpt), "steps": res["steps"], "seconds": round(res["seconds"], 2),
                   "cpu_seconds": round(res["cpu_seconds"], 2),
                   "it_per_s": round(res["steps"] / max(res["seconds"], 1e-9), 4),
                   "cpu_s_per_it": round(res["cpu_seconds"] / max(res["steps"], 1), 4),
                   "final_loss": float(np.mean(tail)) if tail else None,
                   "cached_seconds": round(res["resumed_seconds"], 2),
                   "trainable_parameters": sum(p.numel() for p in params),
                   "device": str(acc.device), "processes": acc.num_processes,
                   "mixed_precision": acc.mixed_precision, "micro_batches": m.config.micro_batches,
                   "grad_checkpointing": m.config.grad_checkpointing, "compile": m.config.compile}
        if anneal_from is not None:
            summary["anneal_steps"] = steps - anneal_from
        m.took_from_cache(res["resumed_seconds"])
        if acc.is_main_process:
            outputfiles.write_json(m.workdir / "training.json", {**m.training, entry or stage: summary})
            outputfiles.write_json(m.workdir / "config.json", m.config_dict())
        m.training[entry or stage] = summary
        return summary

    def base(self) -> tuple[core.ControlledUNet, dict]:
        """Stage 1: (the model, with its base UNet trained where one is, its identity)."""
        c, d = self.m.config, self.data
        cfg = c.core
        model = core.build_model(cfg, control=False, seed=self.m.seed)
        if c.grad_checkpointing:  # activations recomputed in backward (memory, not results)
            model.unet.enable_gradient_checkpointing()
        key = {"core": core.core_key(cfg), "batch": c.base_batch, "lr": c.base_lr, "seed": self.m.seed,
               "data": d.data_hash, "ema": c.ema_decay, "snr_gamma": c.snr_gamma,
               # autocast changes every stage's numbers (fp32 runs keep their older keys)
               **({"precision": self.acc.mixed_precision} if self.acc.mixed_precision != "no" else {})}
        # Only a ControlNet branch trained from scratch has a base stage (a pretrained UNet
        # replaces it; a concat-conditioned UNet is trained whole in the ACM stage).
        has_base = cfg.conditioning == "controlnet" and not cfg.pretrained
        if has_base:
            params = core.trainable(model, ["unet.", "prompt"])

            def base_loss(net, g, part):
                idx = torch.randint(0, d.n, (c.base_batch,), generator=g, device=g.device)
                return train.denoise_loss(net, self.sched, d.z0[idx], None, g, part=part, snr_gamma=self.gamma)

            self.run("base", model, params, base_loss, c.base_steps, c.base_lr, key)
        return model, {**key, "steps": c.base_steps if has_base else 0}

    def acm(self, model, base_id: dict, guidance) -> dict:
        """Stage 2 on `model` (from `base`): the condition's way in, trained with the guidance
        part's dropped conditions; returns the stage's identity."""
        c, d = self.m.config, self.data
        cfg = c.core
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.m.seed + 1)
            model.add_control()
        if c.grad_checkpointing and model.controlnet is not None:
            model.controlnet.enable_gradient_checkpointing()
        key = {"base": base_id, "batch": c.acm_batch, "lr": c.acm_lr, "condition": c.condition,
               "cond": d.cond_hash, **guidance.key()}
        # A concat UNet is trained whole, with its learned text embeddings (a pretrained one's
        # CLIP encodings stay frozen).
        texts = [] if cfg.pretrained else ["prompt"] + (["null_prompt"] if cfg.null_prompt else [])
        params = core.trainable(model, ["controlnet."] if cfg.conditioning == "controlnet" else ["unet.", *texts])

        def acm_loss(net, g, part):
            idx = torch.randint(0, d.n, (c.acm_batch,), generator=g, device=g.device)
            z, k = train.crops(g, c.train_crop, d.z0[idx], d.cond[idx])
            k, text = guidance.drop(k, g)
            return train.denoise_loss(net, self.sched, z, k, g, part=part, snr_gamma=self.gamma, text=text)

        if not c.acm_anneal:
            self.run("acm", model, params, acm_loss, c.acm_steps, c.acm_lr, key)
        else:
            # constant-rate steps (a stage any longer run shares), then the decay phase from them
            stable = c.acm_steps - c.acm_anneal  # >= 1 (checked by the method)
            const_key, key = key, {"acm": {**key, "steps": stable}, "anneal": c.acm_anneal}
            final = stage_ckpt("acm-anneal", key, c.acm_steps)
            if not final.is_file():
                const = self.run("acm", model, params, acm_loss, stable, c.acm_lr, const_key)
                # the decay stage reports the constant steps' seconds as resumed (cached) seconds:
                # take off exactly those (the checkpoint's clock, a little short of the stage's
                # own: subtracting the stage's seconds made a fresh run's cached time negative)
                self.m.took_from_cache(-train.seed_stage(final.parent, Path(const["checkpoint"])))
            self.run("acm-anneal", model, params, acm_loss, c.acm_steps, c.acm_lr, key, anneal_from=stable,
                     entry="acm")
        core.trainable(model, [])
        return {**key, "steps": c.acm_steps}

    def vcm(self, acm, acm_id: dict, scenes: list):
        """Stage 3: clip attention in the UNet's down and up blocks of a copy of the frozen ACM;
        only those layers' projections are trained (the ACM keeps its own, for frame 1)."""
        c, d = self.m.config, self.data
        seqs = d.sequences(scenes)
        f_clip = min(c.clip_frames, min(len(q) for q in seqs))
        vmodel = copy.deepcopy(acm)
        vcm.install_vcm(vmodel, vcm.ClipContext(keys=c.vcm_keys), local_window=c.vcm_local, levels=c.vcm_levels,
                        seed=self.m.seed + 2)
        params = core.trainable(vmodel, vcm.vcm_parameter_names(vmodel))
        key = {"acm": acm_id, "batch": c.vcm_batch, "lr": c.vcm_lr, "frames": f_clip, "layers": list(vcm.VCM_BLOCKS),
               # the paper's wiring keeps the keys its stages had before these existed
               **({"keys": c.vcm_keys} if c.vcm_keys != "clip" else {}),
               **({"local": c.vcm_local} if c.vcm_local else {}),
               **({"levels": c.vcm_levels} if c.vcm_levels else {}),
               **({"crop": c.vcm_crop} if c.vcm_crop >= 0 else {}),
               **({"snr_gamma": c.vcm_snr_gamma} if c.vcm_snr_gamma >= 0 else {})}
        crop = c.train_crop if c.vcm_crop < 0 else c.vcm_crop
        gamma = self.gamma if c.vcm_snr_gamma < 0 else c.vcm_snr_gamma

        def vcm_loss(net, g, part):
            rows = []
            for _ in range(c.vcm_batch):
                q = seqs[int(torch.randint(0, len(seqs), (1,), generator=g, device=g.device))]
                s0 = int(torch.randint(0, len(q) - f_clip + 1, (1,), generator=g, device=g.device))
                rows.append(q[s0:s0 + f_clip])
            idx = torch.tensor(rows, device=d.z0.device)  # [B, F]
            z, k = train.crops(g, crop, d.z0[idx], d.cond[idx])
            with vcm.clip_frames(vmodel, f_clip):
                return train.clip_denoise_loss(net, self.sched, z, k, g, part=part, snr_gamma=gamma)

        self.run("vcm", vmodel, params, vcm_loss, c.vcm_steps, c.vcm_lr, key)
        core.trainable(vmodel, [])
        return vmodel

