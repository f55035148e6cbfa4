"""What a leaderboard row is (`leaderboard.kinds`): its kind from the results' config, else the
paper's kind of its method id, else "beyond"; its components from the config, else derived from the
legacy config fields its run recorded (the committed results files); a bad config kind or
component list is a one-line error naming the field. The rendered board: test_leaderboard.py."""

import json
from pathlib import Path

import pytest
from conftest import ROOT

from skyeyes_bench.errors import UserError
from skyeyes_bench.leaderboard import checks
from skyeyes_bench.leaderboard.kinds import label, legacy_components, row_components, row_kind

RESULTS = ROOT / "leaderboard" / "results"


LEGACY = Path(__file__).parent / "data" / "legacy"


def _config(name: str) -> tuple[str, dict]:
    """(method, config) of the synthtown@3 row `name` as filed before kinds existed: the committed
    results file `name`.json, or for the rows re-filed since (skyeyes, skyeyes-no-vcm) its
    submission's method and config as committed at fc6f72c (data/legacy/)."""
    kept = LEGACY / f"{name}-synthtown3-submission.json"
    s = json.loads(kept.read_text()) if kept.is_file() else json.loads((RESULTS / f"{name}.json").read_text())["submission"]
    assert "kind" not in s["config"], f"{name}: not a legacy row"
    return s["method"], s["config"]


def test_kind_from_config_wins_over_the_method_id():
    assert row_kind("skyeyes", {"kind": "beyond"}) == "beyond"
    assert row_kind("mean-frame", {"kind": "baseline", "acm_steps": 1}) == "baseline"
    assert row_kind("skyeyes-geo", {"kind": "paper"}) == "paper"


@pytest.mark.parametrize("method, kind", [
    ("skyeyes", "paper"), ("skyeyes-no-vcm", "ablation"), ("mvs", "baseline"), ("nerf", "baseline"),
    ("gaussians3d", "baseline"), ("sugar", "baseline"), ("controlnet", "baseline"), ("ip2p", "baseline"),
    ("gvg", "baseline"), ("mean-frame", "floor"), ("skyeyes-geo", "beyond"), ("skyeyes-geo-no-vcm", "beyond"),
    ("my-method", "beyond"), ("None", "beyond")])
def test_kind_of_a_legacy_row_is_its_method_ids(method, kind):
    assert row_kind(method, {"preset": "small"}) == row_kind(method, None) == kind


def test_a_legacy_row_of_the_papers_method_with_our_steps_is_beyond_the_paper():
    """The committed synthtown@3 `skyeyes` row ran carried noise and three steps after sampling
    (legacy fields): not the paper's method, whatever its id; without them it is the paper's."""
    method, cfg = _config("skyeyes")
    assert "kind" not in cfg and row_kind(method, cfg) == "beyond"
    plain = {k: v for k, v in cfg.items() if k not in ("vcm_noise_flow", "vcm_anchor", "vcm_street", "vcm_sky")}
    assert row_kind(method, plain) == "paper"
    assert row_kind(method, {**plain, "vcm_sky": 1}) == "beyond"
    assert row_kind(method, {**plain, "vcm_noise_flow": True, "vcm_noise": 1}) == "beyond"


def test_kind_labels_are_short():
    assert [label(k) for k in ("paper", "ablation", "baseline", "floor", "beyond")] == [
        "paper", "paper's ablation", "paper baseline", "floor", "beyond the paper"]


def test_components_from_config_are_used_verbatim():
    _, cfg = _config("skyeyes")  # legacy fields that would derive other components
    cfg = {**cfg, "components": ["condition: x", "ACM", "my step; with a semicolon"]}
    assert row_components("skyeyes", cfg) == ["condition: x", "ACM", "my step; with a semicolon"]
    assert row_components("skyeyes", {**cfg, "components": []}) == []


def test_legacy_skyeyes_lists_every_step_it_ran_and_its_ablation_none():
    """The committed `skyeyes` row ran noise carried along the flow, the prior anchor, the street
    from one view and the sky from one fit (vcm_noise_flow, vcm_anchor, vcm_street, vcm_sky);
    the committed ablation ran none of them, from pure Gaussian noise."""
    steps = ["carried noise", "prior anchor", "street from one view", "sky from one fit"]
    full = row_components(*_config("skyeyes"))
    assert all(s in full for s in steps), full
    assert "pure Gaussian noise" not in full
    assert full == ["condition: the sugar prior's renders", "ACM", "VCM (12-frame clips after the first frame)", *steps]
    ablation = row_components(*_config("skyeyes-no-vcm"))
    assert not any(s in ablation for s in steps), ablation
    assert ablation == ["condition: the sugar prior's renders", "ACM frame by frame", "pure Gaussian noise"]


def test_legacy_baselines_say_what_they_condition_on():
    assert row_components(*_config("controlnet")) == [
        "condition: the nearest aerial view", "ACM frame by frame", "pure Gaussian noise"]
    # the words the methods' own `components()` record today (reference/methods/*.py)
    assert row_components(*_config("ip2p"))[:2] == [
        "condition: the nearest aerial view, with the instruction 'turn the aerial view into a realistic street view "
        "image'", "classifier-free guidance on image and text (scales 1.5, 7.5)"]
    assert row_components(*_config("gvg"))[0] == (
        "condition: the mvs cloud's projected aerial texture, inverse depth and coverage mask")
    assert row_components(*_config("mean-frame")) == ["every frame the per-pixel mean of the train split's ground frames"]
    mapped = "colours mapped as learned on the train split"
    assert row_components(*_config("mvs")) == ["SfM and plane-sweep multi-view stereo on the lane's aerial views",
                                               "the fused cloud's discs rendered at the ground cameras", mapped]
    assert row_components(*_config("nerf")) == ["Instant-NGP field fitted on the lane's aerial views",
                                                "rendered at the ground cameras", mapped]
    assert row_components(*_config("gaussians3d")) == ["3D Gaussian splatting fitted on the lane's aerial views",
                                                       "rendered at the ground cameras", mapped]
    assert row_components(*_config("sugar")) == ["SuGaR: surface-aligned 3D Gaussians fitted on the lane's aerial views",
                                                 "rendered at the ground cameras", mapped]


def test_legacy_derivation_by_field():
    base = {"acm_steps": 10, "condition": "prior", "prior_method": "gaussians3d", "vcm": True}
    assert legacy_components("skyeyes-geo", base) == [
        "condition: the gaussians3d prior's renders", "ACM", "VCM (12-frame clips after the first frame)", "pure Gaussian noise"]
    # carried noise needs both the flow and a non-zero amount; post-sampling steps only when non-zero
    assert "pure Gaussian noise" in legacy_components("x", {**base, "vcm_noise_flow": True, "vcm_noise": 0})
    assert "pure Gaussian noise" in legacy_components("x", {**base, "vcm_noise_flow": False, "vcm_noise": 1})
    assert legacy_components("x", {**base, "vcm_anchor": 0, "vcm_street": 0.5, "vcm_sky": 0})[-2:] == [
        "pure Gaussian noise", "street from one view"]
    assert legacy_components("my-method", {"iterations": 3}) == legacy_components("my-method", None) == []


@pytest.mark.parametrize("config, field", [
    ({"kind": "method"}, "'submission.config.kind'"), ({"kind": 3}, "'submission.config.kind'"),
    ({"kind": "Paper"}, "'submission.config.kind'"),
    ({"components": "ACM; VCM"}, "'submission.config.components'"),
    ({"components": ["ACM", ""]}, "'submission.config.components[1]'"),
    ({"components": ["ACM", 7]}, "'submission.config.components[1]'"),
    ({"components": ["two\nlines"]}, "'submission.config.components[0]'")])
def test_bad_kind_or_components_is_one_line_naming_the_field(config, field):
    with pytest.raises(UserError) as e:
        checks.method_config("r.json", config)
    assert str(e.value).startswith(f"r.json: field {field}") and "\n" not in str(e.value), str(e.value)
    if "kind" in config:
        assert "paper, ablation, baseline, floor, beyond" in str(e.value)


def test_good_or_absent_kind_and_components_pass():
    for config in (None, "odd", {}, {"kind": None, "components": None}, {"kind": "beyond", "components": []},
                   {"kind": "floor", "components": ["per-pixel mean"]}):
        checks.method_config("r.json", config)
