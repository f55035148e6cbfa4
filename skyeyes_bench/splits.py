"""The three splits of a protocol: train (fitted on), val (settings chosen on), test (reported on,
ranked). Tune on validation, report on test (docs/evaluate.md, "The split").

A run on the validation split sees its dataset through `scored_view`: "train" is what it fits on
and "test" the validation scenes it scores, so every stage after it (fit, render, submission,
evaluate) is the test run's, and the submission and results say `split: "val"`. Where the
validation split comes from is the protocol family's `val.toml` (`protocol.ValSpec`): towns of
their own in a dataset of their own (SynthTown's `<dataset>-val`, made with `data synthtown
--split val`), or a declared part of the train towns, which the run then leaves out of training.

A tool that screens settings (bench/, any search) calls `screening_split`, which refuses the test
split in one line.

What a dataset's splits must hold to be scored is one rule (`scored_scenes`), which `scored_view`
(evaluate, submission template) and `check_scorable` (data check) both apply: a dataset that
`data check` passes is never refused by `evaluate` for its splits.
"""

from __future__ import annotations

import dataclasses

from .errors import UserError

#: The splits a submission may hold, and a results file score.
SCORED = ("test", "val")


def check_split(split: str, flag: str = "--split") -> str:
    """`split` if it is one a run can score ("test", "val"); else a one-line UserError."""
    if split not in SCORED:
        raise UserError(f"{flag} {split!r}: expected one of {', '.join(SCORED)}")
    return split


def scored_view(ds, split: str, protocol=None):
    """`ds` as a run on `split` sees it: "test", `ds` itself; "val", a view whose "train" is the
    train scenes less the validation scenes and whose "test" is the validation scenes: the
    dataset's own "val" split (SynthTown's validation data), else the train scenes of the towns
    `protocol.val` declares (scene meta "town"; source "train")."""
    check_split(split)
    if split == "test":
        scored_scenes(ds, "test")
        return ds
    train = ds.splits.get("train", ())
    if "val" in ds.splits:
        val = scored_scenes(ds, "val")
    else:
        spec = getattr(protocol, "val", None)
        if spec is None or spec.source != "train":
            where = f"protocol {protocol.ref}" if protocol is not None else "its protocol"
            raise UserError(f"{ds.root}/dataset.json: dataset {ds.name!r} has no 'val' split and {where} declares none "
                            "in its train towns; make the validation data (`skyeyes-bench data synthtown --split val`) "
                            "or import a dataset whose train towns hold the protocol's validation towns")
        val = tuple(s for s in train if ds.scenes[s].meta.get("town") in spec.towns)
        if not val:
            raise UserError(f"{ds.root}/dataset.json: no train scene of dataset {ds.name!r} lies in the validation "
                            f"towns {', '.join(spec.towns)} of protocol {protocol.ref} (scene.json field 'meta.town')")
    return dataclasses.replace(ds, splits={"train": tuple(s for s in train if s not in val), "test": tuple(val)},
                               scored="val")


def scored_scenes(ds, split: str) -> tuple[str, ...]:
    """The scenes of dataset `ds`'s split `split` ("test", or a dataset's own "val"); a one-line
    UserError naming dataset.json and the field when the split is missing or lists no scene:
    there would be nothing to score."""
    members = ds.splits.get(split)
    if members:
        return tuple(members)
    what = "is empty" if split in ds.splits else f"is missing (splits: {', '.join(ds.splits) or 'none'})"
    run = "evaluate scores and ranks" if split == "test" else "a run on the validation split scores"
    raise UserError(f"{ds.root}/dataset.json: field 'splits.{split}' {what}; expected the list of the {split} "
                    f"scenes, which {run}")


def check_scorable(ds) -> str:
    """The split dataset `ds` is made to be scored on, checked as `scored_view` checks it for
    evaluate (what `data check` applies): "test"; "val" for validation data of its own (a 'val'
    split and no 'test' one: SynthTown's `<dataset>-val`). A validation split that a protocol
    declares in its train towns (CARLA, CitySample) is checked where a run asks for it."""
    split = "val" if "val" in ds.splits and "test" not in ds.splits else "test"
    scored_view(ds, split)
    return split


def screening_split(split: str, what: str) -> str:
    """The split a tool that screens settings (`what`, e.g. "bench/additions.py") may run on:
    "val"; "test" is refused in one line (a setting chosen on the test split has seen the numbers it
    is reported with)."""
    if split == "test":
        raise UserError(f"{what} screens settings, so it runs on the validation split only (--split val): "
                        "settings chosen on the test split are tuned to the numbers they are reported with")
    return check_split(split)
