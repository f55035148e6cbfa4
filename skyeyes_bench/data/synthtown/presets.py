"""Named SynthTown configurations (a preset is a named config, saved with the run).

Kept free of numpy so that the CLI can list presets without importing the renderer.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass


@dataclass(frozen=True)
class Preset:
    """What one `skyeyes-bench data synthtown --preset NAME` writes.

    Attributes:
        name: preset id.
        width, height: image size in pixels, ground and aerial alike.
        fov_deg: horizontal field of view (protocol synthtown@1: 90 deg).
        aa: supersampling: 1 = one ray per pixel (its centre); 2 = the centre plus a 2x2 grid
            (5 rays, "quincunx"); 3 = a 3x3 grid (9 rays, centre included). Colour is averaged
            over all rays in linear light; depth and labels come from the centre ray.
        blocks: street-grid blocks per town along x and y.
        lanes: {town name: lanes rendered}; train towns first, then the test town.
        frames: ground points per lane (one every `step_m` metres); every sequence has this many
            frames (>= 16, the FVD clip length).
        aerial_stride: an aerial camera group every `aerial_stride` ground points.
        aerial_yaws: how many headings per aerial group (k * 360 / aerial_yaws deg from the lane
            direction); 8 follows the paper's k*pi/4.
        cull_m: distance culling radius in metres (objects farther away are not tested; the haze
            has swallowed them by then).
        official: the protocol's official data (its scores go on the leaderboard).
        protocol: the protocol the data is made for ("synthtown@1" or "synthtown@2").
        dataset: the dataset's name (and folder under `<cache>/data/`).
    """

    name: str
    width: int
    height: int
    aa: int
    blocks: tuple[int, int]
    lanes: tuple[tuple[str, int], ...]
    frames: int
    aerial_stride: int
    aerial_yaws: int = 8
    fov_deg: float = 90.0
    step_m: float = 2.0
    ground_height_m: float = 2.0
    aerial_height_m: float = 52.0
    aerial_pitch_deg: float = -45.0
    cull_m: float = 220.0
    official: bool = False
    protocol: str = "synthtown@2"
    dataset: str = ""

    def to_dict(self) -> dict:
        """What the generator renders from (dataset.json's preset_config); protocol and dataset
        names are recorded elsewhere in dataset.json, so v1 data keeps its bytes."""
        d = dataclasses.asdict(self)
        del d["protocol"], d["dataset"]
        d["blocks"] = list(self.blocks)
        d["lanes"] = {t: n for t, n in self.lanes}
        return d


TRAIN_TOWNS = ("train-0", "train-1")
TEST_TOWNS = ("test-0",)
#: The validation towns: towns of their own (their name seeds their own random stream), never
#: trained on or ranked; where a method's settings are chosen (`--split val`,
#: protocols/synthtown/val.toml).
VAL_TOWNS = ("val-0",)
#: The splits a SynthTown dataset can be made for: "test" (the protocol's train and test towns)
#: or "val" (the same train towns and the validation towns, in a dataset of its own, so the
#: ranked data stays byte for byte what it was).
SPLITS = ("test", "val")

PRESETS: dict[str, Preset] = {
    # Tests and CI: one train lane, one test lane, 16-frame sequences, tiny images (synthtown@1:
    # with one test lane, v2's scene statistics could only say "too few scenes").
    "smoke": Preset("smoke", 48, 48, aa=1, blocks=(3, 3), lanes=(("train-0", 1), ("test-0", 1)),
                    frames=16, aerial_stride=8, aerial_yaws=4, protocol="synthtown@1", dataset="synthtown-smoke"),
    # synthtown@2's official data and the CPU default for `reproduce` (docs/synthtown.md, "Protocol
    # v2"): 8 test lanes, so intervals resample 8 scenes; 32-frame sequences, so FVD sees 2
    # non-overlapping 16-frame clips per sequence; a 5x5-block town so 8 lanes fit on distinct
    # street sides.
    "small": Preset("small", 128, 128, aa=2, blocks=(5, 5),
                    lanes=(("train-0", 2), ("train-1", 2), ("test-0", 8)),
                    frames=32, aerial_stride=4, aerial_yaws=8, official=True, dataset="synthtown-v2-small"),
    # synthtown@1's official data (2 test lanes, 20-frame sequences), kept so v1 results reproduce.
    "small-v1": Preset("small-v1", 128, 128, aa=2, blocks=(4, 4),
                       lanes=(("train-0", 2), ("train-1", 2), ("test-0", 2)),
                       frames=20, aerial_stride=4, aerial_yaws=8, official=True, protocol="synthtown@1",
                       dataset="synthtown-small"),
    # synthtown-stiff@1's data (docs/synthtown.md, "Stiff towns"): `small` with its test town
    # replaced by a tilted, cloudy one (town.STIFF), where the street is no level plane and the
    # sky no smooth function of the direction; the same train towns.
    "small-stiff": Preset("small-stiff", 128, 128, aa=2, blocks=(5, 5),
                          lanes=(("train-0", 2), ("train-1", 2), ("stiff-0", 8)),
                          frames=32, aerial_stride=4, aerial_yaws=8, protocol="synthtown-stiff@1",
                          dataset="synthtown-v2-small-stiff"),
    # Paper-sized images and fuller counts (GPU users; hours on a CPU).
    "paper": Preset("paper", 512, 512, aa=3, blocks=(5, 5),
                    lanes=(("train-0", 6), ("train-1", 6), ("test-0", 8)),
                    frames=32, aerial_stride=2, aerial_yaws=8, dataset="synthtown-v2-paper"),
}


def for_split(p: Preset, split: str) -> Preset:
    """The preset of `p`'s dataset for `split`: "test", `p` itself; "val", the same train towns
    and as many lanes of the validation towns as `p` has test lanes, in a dataset of its own
    (`<dataset>-val`), never official."""
    if split not in SPLITS:
        raise ValueError(f"split {split!r}: expected one of {', '.join(SPLITS)}")
    if split == "test":
        return p
    train = tuple((t, n) for t, n in p.lanes if t in TRAIN_TOWNS)
    n_test = sum(n for t, n in p.lanes if t not in TRAIN_TOWNS)
    return dataclasses.replace(p, name=f"{p.name}-val", lanes=train + tuple((t, n_test) for t in VAL_TOWNS),
                               official=False, dataset=f"{p.dataset}-val")
