"""`ScoringRun`: what one scoring run scores, and what its stages record."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

from ..inputfiles import sha256_file
from ..results import progress_bar, timed_stage
from ..submission import frame_relpath


@dataclass
class ScoringRun:
    """One scoring run: its inputs, which the stages (`frames.score_frames`,
    `frames.score_sequences`, `features.features`) read, and what they record into it through
    the methods: seconds per stage (`time`), the metrics that cannot be computed here
    (`mark_unavailable`) and one record per scored frame (`add_record`, `add_values`)."""

    sub: Path  # the submission folder
    ds: Any  # data.layout.Dataset, seen as the split it scores
    protocol: Any  # protocol.Protocol
    seq_ids: list[str]  # "<scene>/<sequence>" of every sequence of the split, in order
    frames: list[tuple[str, Any]]  # (scene, frame) this run scores: whole sequences of its shard
    sub_sha: dict[str, str]  # relative path -> sha256 of every submitted frame (hashed once)
    device: Any = None  # torch.device of the feature extractors
    progress: bool = False  # progress bars on stderr
    timing: dict[str, float] = field(default_factory=dict)  # stage -> seconds
    unavailable: dict[str, dict] = field(default_factory=dict)  # metric -> {"reason", "fix"}
    records: list[dict] = field(default_factory=list)  # one per scored frame, in `frames` order
    seq_index: dict[str, int] = field(init=False)  # "<scene>/<sequence>" -> its number
    _record_of: dict[tuple[str, str], dict] = field(init=False, repr=False, default_factory=dict)

    def __post_init__(self):
        self.seq_index = {sid: k for k, sid in enumerate(self.seq_ids)}

    # ----------------------------------------------------------------------- what it reads

    def specs(self, names: Iterable[str]) -> list:
        """The protocol's `MetricSpec`s of those of `names` it asks for, in the order of `names`."""
        return [m for m in (self.protocol.metric(n) for n in names) if m is not None]

    def pred_path(self, scene: str, frame) -> Path:
        """The submitted file of `frame` of `scene`."""
        return self.sub / frame_relpath(scene, frame)

    def sequence_of(self, scene: str, frame) -> int:
        """The number of the sequence `frame` belongs to."""
        return self.seq_index[f"{scene}/{frame.sequence}"]

    def bar(self, total: int, desc: str, unit: str):
        """A progress bar (drawn only when the run shows progress)."""
        return progress_bar(self.progress, total=total, desc=desc, unit=unit)

    # ----------------------------------------------------------------------- what it records

    def time(self, stage: str):
        """Context manager: adds the seconds spent inside to `stage` (e.g. "features_s")."""
        return timed_stage(self.timing, stage)

    def start_clock(self, stage: str) -> None:
        """List `stage` now, at 0 s: reported even when nothing inside it runs."""
        self.timing.setdefault(stage, 0.0)

    def mark_unavailable(self, names: Iterable[str], reason: str, fix: str) -> None:
        """The metrics `names` cannot be computed here: why, and what would fix it."""
        for name in names:
            self.unavailable[name] = {"reason": reason, "fix": fix}

    def is_unavailable(self, name: str) -> bool:
        return name in self.unavailable

    def add_record(self, scene: str, frame, values: dict[str, float]) -> None:
        """The record of `frame`: where it is, the hashes of both files, then `values`."""
        rec = {"scene": scene, "file": frame.file, "sequence": self.sequence_of(scene, frame),
               "index": int(frame.index), "sha256": self.sub_sha[frame_relpath(scene, frame)],
               "gt_sha256": sha256_file(frame.path), **values}
        self.records.append(rec)
        self._record_of[(scene, frame.file)] = rec

    def add_values(self, scene: str, frame, values: dict[str, Any]) -> None:
        """More values in the record of `frame` (made by `add_record`)."""
        self._record_of[(scene, frame.file)].update(values)

