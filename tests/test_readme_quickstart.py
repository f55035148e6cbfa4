"""The README's quickstart, run as written on smoke data (issue 58): its five commands, with only
the data made smaller (`--preset smoke`), the committed row it compares with replaced by a
second submission scored on the same smoke data, and the board it files into a copy."""

import json
import re
import shlex
import shutil
from pathlib import Path

import pytest

from conftest import ROOT, run_cli

COMMITTED_ROW = "leaderboard/results/skyeyes-synthtown4.json"
CACHE_DATA = "~/.cache/skyeyes-bench/data/synthtown-v2-small"


def quickstart() -> list[list[str]]:
    """The command lines of README.md's Quickstart block, each split as a shell would (comments
    dropped)."""
    text = (ROOT / "README.md").read_text()
    section = text.split("## Quickstart", 1)[1]
    block = re.search(r"```\n(.*?)```", section, re.S).group(1)
    return [shlex.split(line, comments=True) for line in block.splitlines() if line.strip()]


def test_readme_quickstart_has_five_commands_in_order():
    cmds = quickstart()
    assert [c[0] for c in cmds] == ["skyeyes-bench"] * 5
    assert [c[1:3] for c in cmds] == [["data", "synthtown"], ["submission", "template"], ["evaluate", "sub"],
                                      ["compare", "sub.results.json"], ["leaderboard", "add"]]
    assert COMMITTED_ROW in cmds[3] and (ROOT / COMMITTED_ROW).is_file()  # the row it names is committed
    # the data the template reads is where `data synthtown --preset small` writes it
    assert CACHE_DATA in cmds[1]
    from skyeyes_bench.paths import cache_dir

    assert Path(CACHE_DATA.replace("~/.cache/skyeyes-bench", str(cache_dir()))).name == "synthtown-v2-small"


@pytest.mark.slow  # two smoke evaluations: ~1-4 min on 2 shared cores
def test_readme_quickstart_runs_on_smoke_data(tmp_path, monkeypatch):
    from builders import weights as real_weights
    from skyeyes_bench.metrics.weights import WEIGHT_FILES

    real_weights.require(*WEIGHT_FILES)  # the README's set-up fetched them all
    monkeypatch.chdir(tmp_path)
    board = tmp_path / "board"
    (board / "results").mkdir(parents=True)
    from skyeyes_bench.paths import cache_dir

    data = cache_dir() / "data" / "synthtown-smoke"  # where `data synthtown --preset smoke` writes (this test's cache)
    cmds = quickstart()

    def edit(cmd: list[str]) -> list[str]:
        out = []
        for a in cmd[1:]:
            a = {"small": "smoke", CACHE_DATA: str(data), COMMITTED_ROW: "other.results.json"}.get(a, a)
            out.append(a)
        if cmd[1:3] == ["data", "synthtown"]:
            out += ["--quiet"]
        if cmd[1:3] == ["leaderboard", "add"]:
            out += ["--root", str(board)]
        return out

    run_cli(*edit(cmds[0]))
    run_cli(*edit(cmds[1]))
    # the row to compare with: the same frames, darkened (a worse method on the same data)
    shutil.copytree("sub", "other")
    from skyeyes_bench.imagefiles import read_image_uint8, write_image

    for p in sorted(Path("other").rglob("*.png")):
        write_image(p, read_image_uint8(p)[..., :3] // 2)
    run_cli("evaluate", "other", "--out", "other.results.json")
    run_cli(*edit(cmds[2]))
    sub = json.loads(Path("sub.results.json").read_text())
    assert sub["metrics"]["psnr"]["status"] == "ok" and sub["metrics"]["lpips"]["value"] < 1e-6  # perfect
    _, out, _ = run_cli(*edit(cmds[3]))
    assert "psnr" in out.lower() and "lpips" in out.lower()
    run_cli(*edit(cmds[4]))
    filed = json.loads((board / "results" / "my-method.json").read_text())
    assert filed["sha256"] == sub["sha256"] and filed["metrics"] == sub["metrics"]
