"""The scripts of bench/ as a user runs them (a process each, the project's python, in the
repository): every one answers --help, and every one that screens settings refuses the test
split in one line that names the validation split, with exit 2 (tune on validation,
report on test: docs/evaluate.md, "The split"). bench/warp.py, which compares submissions, refuses a submission
on the test split."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"
PYTHON = ROOT / ".venv" / "bin" / "python"
if not PYTHON.is_file():  # an install without the repository's venv: the python running the tests
    PYTHON = Path(sys.executable)

SCRIPTS = sorted(p.stem for p in BENCH.glob("*.py"))

#: The scripts that screen settings, and the arguments that ask each for the test split (beside
#: what it needs to get that far; `additions` reads its run folder first: see `_fake_run`).
SCREENS = {
    "additions": ["--split", "test", "--run", "{run}", ""],
    "vcm_screen": ["--split", "test", ""],
    "flow_accuracy": ["--split", "test", "--priors", "{tmp}", "--ways", "zero"],
    "mvs": ["--split", "test"],
    "nerf": ["fit", "--split", "test"],
    "gaussians": ["fit", "--split", "test"],
    "skyeyes": ["--split", "test"],
    "depth_metrics": ["--split", "test"],
}


def _run(args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([str(PYTHON), *args], capture_output=True, text=True, cwd=ROOT)


def test_the_lists_name_scripts_that_exist():
    assert set(SCREENS) <= set(SCRIPTS)
    assert len(SCRIPTS) >= 18  # bench/ holds 18 scripts as this test is written


@pytest.mark.parametrize("name", SCRIPTS)
def test_help(name):
    r = _run([f"bench/{name}.py", "--help"])
    assert r.returncode == 0, f"bench/{name}.py --help: rc={r.returncode}\n{r.stderr[-3000:]}"
    assert r.stdout.lstrip().startswith("usage:"), r.stdout[:500]
    assert "Traceback" not in r.stderr


def _fake_run(tmp: Path) -> Path:
    """What bench/additions.py reads of a `reproduce --split val` folder before it screens: its
    config.json (steps after sampling off) and its prior's fitted scenes folder."""
    run = tmp / "run"
    (run / "work" / "key" / "method" / "prior" / "scenes").mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"dataset": {"split": "val", "root": str(tmp / "no-data")},
                                                 "config": {}, "cache_key": "key", "seed": 0}))
    return run


@pytest.mark.parametrize("name", sorted(SCREENS))
def test_a_screen_refuses_the_test_split(name, tmp_path):
    args = [a.format(run=_fake_run(tmp_path) if "{run}" in a else "", tmp=tmp_path) for a in SCREENS[name]]
    r = _run([f"bench/{name}.py", *args])
    lines = r.stderr.splitlines()
    assert r.returncode == 2, f"bench/{name}.py {' '.join(args)}: rc={r.returncode}\n{r.stderr[-3000:]}"
    assert len(lines) == 1, r.stderr[-3000:]
    assert "validation split" in lines[0] and "test" in lines[0], lines[0]
    assert "Traceback" not in r.stderr


def test_warp_refuses_a_test_split_submission(tmp_path, monkeypatch):
    from builders.evaluation import blurred_submission, install_test_protocol, make_dataset

    from skyeyes_bench.data.layout import open_dataset

    install_test_protocol(tmp_path, monkeypatch)
    ds = open_dataset(make_dataset(tmp_path / "ds", scenes=1, seqs=1, frames=2, size=16))
    sub = blurred_submission(ds, tmp_path / "sub")
    assert json.loads((sub / "submission.json").read_text())["dataset"]["split"] == "test"
    r = _run(["bench/warp.py", "--data", str(tmp_path / "ds"), str(sub)])
    lines = r.stderr.splitlines()
    assert r.returncode == 2, r.stderr[-3000:]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr[-3000:]
    assert str(sub / "submission.json") in lines[0] and "dataset.split" in lines[0]
    assert "validation split" in lines[0]
    assert not r.stdout


def _additions_script():
    import importlib.util

    spec = importlib.util.spec_from_file_location("bench_additions", BENCH / "additions.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_an_additions_setting_is_its_steps_in_the_pipelines_order_with_the_rest_off():
    """A setting turns on only the steps it names, whatever `skyeyes-geo`'s preset holds, and in
    the order the pipeline runs them (anchor, street, sky) however it is written."""
    mod = _additions_script()
    assert mod.setting_additions("small", "") == []
    steps = mod.setting_additions("small", "sky.mix=1 anchor.mix=0.3")
    assert [s.name for s in steps] == ["prior anchor", "sky from one fit"]
    assert steps[0].cfg.mix == 0.3 and steps[1].cfg.mix == 1
    names = [s.name for s in mod.setting_additions("small", "street.mix=0.8 street.view_m=8 anchor.mix=0.5 sky.mix=1")]
    assert names == ["prior anchor", "street from one view", "sky from one fit"]


@pytest.mark.parametrize("change, field", [
    ({"dataset": {"split": "test"}}, "dataset.split"),
    ({"config": {"anchor": {"mix": 0.5}}}, "steps after sampling were on"),
])
def test_the_additions_screen_takes_only_a_val_run_with_its_steps_off(tmp_path, change, field):
    from skyeyes_bench.errors import UserError

    mod = _additions_script()
    run = _fake_run(tmp_path)
    cfg = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**cfg, **change}))
    with pytest.raises(UserError, match=field.replace(".", r"\.")):
        mod.run_inputs(run)
    (run / "config.json").write_text(json.dumps(cfg))
    sub, scenes, _ = mod.run_inputs(run)
    assert sub == run / "submission" and scenes == run / "work" / "key" / "method" / "prior" / "scenes"
