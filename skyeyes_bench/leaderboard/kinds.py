"""What a measured row is: its kind (the paper's method, its ablation, a baseline the paper compares
with, the floor, or beyond the paper) and the components its method runs.

A table of scores alone hides both: a reader cannot tell the paper's method from a variant of it,
nor see that two rows of one method ran different parts (noise carried along the flow, a prior
anchor). Results written since say so in `submission.config` ("kind", "components"); for results
filed before, both are derived here from the method id and the config fields those runs recorded,
so old rows still say what they are.
"""

from __future__ import annotations

from .. import fields

#: kind -> (the label the board prints in its Kind column, what the kind means).
KINDS = {
    "paper": ("paper", "the paper's method"),
    "ablation": ("paper's ablation", "the paper's ablation of its method"),
    "baseline": ("paper baseline", "a baseline from the paper (its Tables 1-2 compare with it)"),
    "floor": ("floor", "a trivial method every row should beat"),
    "beyond": ("beyond the paper", "a method the paper does not have"),
}

#: Kinds of the method ids the paper has (NOTE: Skyeyes, WACV 2025, Tables 1-2 compare the method
#: with these baselines; the ablation drops the VCM). Any other id is "beyond".
METHOD_KINDS = {
    "skyeyes": "paper",
    "skyeyes-no-vcm": "ablation",
    **dict.fromkeys(("mvs", "nerf", "gaussians3d", "sugar", "controlnet", "ip2p", "gvg"), "baseline"),
    "mean-frame": "floor",
}

#: What the methods outside the diffusion family run (for results without config "components"),
#: in the words their `Method.components()` records today.
_MAPPED = "colours mapped as learned on the train split"
OTHER_COMPONENTS = {
    "mean-frame": ["every frame the per-pixel mean of the train split's ground frames"],
    "mvs": ["SfM and plane-sweep multi-view stereo on the lane's aerial views",
            "the fused cloud's discs rendered at the ground cameras", _MAPPED],
    "nerf": ["Instant-NGP field fitted on the lane's aerial views", "rendered at the ground cameras", _MAPPED],
    "gaussians3d": ["3D Gaussian splatting fitted on the lane's aerial views", "rendered at the ground cameras",
                    _MAPPED],
    "sugar": ["SuGaR: surface-aligned 3D Gaussians fitted on the lane's aerial views",
              "rendered at the ground cameras", _MAPPED],
}

#: Post-sampling steps of the legacy Skyeyes config, each run when its field is non-zero, in the
#: order they were added (docs/skyeyes.md, Results).
_LEGACY_STEPS = (("vcm_anchor", "prior anchor"), ("vcm_street", "street from one view"),
                 ("vcm_sky", "sky from one fit"))


def label(kind: str) -> str:
    """The short label of `kind` (a key of KINDS) for the board's Kind column."""
    return KINDS[kind][0]


#: Components of ours a legacy row of a paper method id may have run: such a row is "beyond".
_OURS = ("carried noise", *(words for _, words in _LEGACY_STEPS))


def row_kind(method: str, config) -> str:
    """The row's kind: the config's "kind" (checked by `checks.results_fields`) when recorded, else
    the paper's kind of `method`, else "beyond"; a legacy row that ran any of our additions under a
    paper method id (the synthtown@3 `skyeyes` rows filed before the method was split) is "beyond"."""
    recorded = config.get("kind") if isinstance(config, dict) else None
    if recorded is not None:
        return recorded
    if any(step in _OURS for step in legacy_components(method, config)):
        return "beyond"
    return METHOD_KINDS.get(method, "beyond")


def row_components(method: str, config) -> list[str]:
    """The components the row's method runs: the config's "components" when recorded, else
    `legacy_components`."""
    recorded = config.get("components") if isinstance(config, dict) else None
    return list(recorded) if recorded is not None else legacy_components(method, config)


def legacy_components(method: str, config) -> list[str]:
    """The components of a run that did not record them, from its method id and config: for the
    diffusion family (a config with `acm_steps`) the condition, the ACM, the VCM, the sampling
    noise and the post-sampling steps that were on; for the others a fixed line per method id;
    [] for an id not known here."""
    c = config if isinstance(config, dict) else {}
    if not fields.is_number(c.get("acm_steps")):
        return list(OTHER_COMPONENTS.get(method, []))
    # ip2p and gvg are checked first: ip2p's condition field is "aerial" too
    guidance = []
    if method == "ip2p":
        cond = f"the nearest aerial view, with the instruction {c.get('core', {}).get('prompt_text', '')!r}"
        guidance = [f"classifier-free guidance on image and text (scales {c.get('image_guidance'):g}, "
                    f"{c.get('text_guidance'):g})"] if all(fields.is_number(c.get(k)) for k in (
                        "image_guidance", "text_guidance")) else ["classifier-free guidance on image and text"]
    elif method == "gvg":
        cond = "the mvs cloud's projected aerial texture, inverse depth and coverage mask"
    elif c.get("condition") == "aerial":
        cond = "the nearest aerial view"
    else:
        cond = f"the {c.get('prior_method') or 'geometric'} prior's renders"
    out = [f"condition: {cond}", *guidance, "ACM" if c.get("vcm") else "ACM frame by frame"]
    if c.get("vcm"):
        clip = c.get("clip_frames") if fields.is_number(c.get("clip_frames")) else 12
        out.append(f"VCM ({clip:g}-frame clips after the first frame)")
    carried = c.get("vcm_noise_flow") is True and fields.is_number(c.get("vcm_noise")) and c["vcm_noise"] > 0
    out.append("carried noise" if carried else "pure Gaussian noise")
    out += [words for key, words in _LEGACY_STEPS if fields.is_number(c.get(key)) and c[key] != 0]
    return out
