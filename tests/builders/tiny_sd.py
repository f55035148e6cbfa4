"""A tiny randomly initialised Stable Diffusion 1.5-layout diffusers folder (no tests here): UNet,
VAE, CLIP text encoder and tokenizer, saved with `save_pretrained`, for the `--pretrained` paths."""

from __future__ import annotations

import json
from pathlib import Path

import torch

RES = 32  # model input: the SD VAE downsamples 8x, so latents are 4x4


def _bytes_to_unicode() -> list[str]:
    """GPT-2 / CLIP byte-level alphabet (Radford et al. 2019): the 256 symbols BPE starts from."""
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + list(range(ord("®"), ord("ÿ") + 1))
    cs, n = bs[:], 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return [chr(c) for c in cs]


#: NOTE: runwayml/stable-diffusion-v1-5 `scheduler/scheduler_config.json`, as published.
SD15_SCHEDULER = {"_class_name": "PNDMScheduler", "_diffusers_version": "0.6.0", "beta_end": 0.012,
                  "beta_schedule": "scaled_linear", "beta_start": 0.00085, "num_train_timesteps": 1000,
                  "set_alpha_to_one": False, "skip_prk_steps": True, "steps_offset": 1,
                  "trained_betas": None, "clip_sample": False}


def make_tiny_sd(root: Path) -> Path:
    """unet/, vae/, text_encoder/, tokenizer/ of a tiny random SD1.5-layout pipeline, and SD1.5's
    own scheduler/."""
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

    torch.manual_seed(0)
    UNet2DConditionModel(sample_size=RES // 8, in_channels=4, out_channels=4, layers_per_block=1,
                         block_out_channels=(8, 16), down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
                         up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"), cross_attention_dim=16,
                         attention_head_dim=2, norm_num_groups=4).save_pretrained(root / "unet")
    AutoencoderKL(in_channels=3, out_channels=3, latent_channels=4, block_out_channels=(4, 4, 4, 4),
                  down_block_types=("DownEncoderBlock2D",) * 4, up_block_types=("UpDecoderBlock2D",) * 4,
                  layers_per_block=1, norm_num_groups=2, sample_size=RES).save_pretrained(root / "vae")
    # No merges: every word is spelt letter by letter ("</w>" marks a word's last letter).
    alphabet = _bytes_to_unicode()
    vocab = {s: i for i, s in enumerate(alphabet + [a + "</w>" for a in alphabet] + ["<|startoftext|>", "<|endoftext|>"])}
    (root / "tok").mkdir(parents=True)
    (root / "tok" / "vocab.json").write_text(json.dumps(vocab))
    (root / "tok" / "merges.txt").write_text("#version: 0.2\n")
    CLIPTokenizer(str(root / "tok" / "vocab.json"), str(root / "tok" / "merges.txt"),
                  model_max_length=77).save_pretrained(root / "tokenizer")
    CLIPTextModel(CLIPTextConfig(vocab_size=len(vocab), hidden_size=16, intermediate_size=32, num_hidden_layers=1,
                                 num_attention_heads=2, max_position_embeddings=77, projection_dim=16,
                                 bos_token_id=vocab["<|startoftext|>"], eos_token_id=vocab["<|endoftext|>"],
                                 pad_token_id=vocab["<|endoftext|>"])).save_pretrained(root / "text_encoder")
    # SD1.5's own scheduler/scheduler_config.json (its values; the folder's model was trained on it)
    (root / "scheduler").mkdir(parents=True)
    (root / "scheduler" / "scheduler_config.json").write_text(json.dumps(SD15_SCHEDULER))
    return root
