"""`skyeyes-bench leaderboard evaluate INBOX/` (issue 38): an inbox of three submissions, one
malformed, files two rows and names the third with its one-line error, and `leaderboard --check`
passes; on Ray and in turn alike. A re-run scores only new or changed folders (sha256), replaces
only results it filed itself, and writes nowhere but the leaderboard root and --out."""

import json
import shutil

import numpy as np
import pytest
from conftest import ROOT, run_cli
from builders.evaluation import blurred_submission, make_dataset, protocol_env, scores

from skyeyes_bench import imagefiles
from skyeyes_bench.leaderboard.intake import STATE_FILE, submission_sha

try:
    import ray  # noqa: F401

    HAVE_RAY = True
except ImportError:
    HAVE_RAY = False


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A 3-scene dataset (test protocol) and an inbox of three submissions: `sharp`, `blurry`, and
    `broken`, whose submission.json says it took -1 s to fit."""
    tmp = tmp_path_factory.mktemp("intake")
    with protocol_env(tmp) as mp:
        from skyeyes_bench.data.layout import open_dataset

        ds = open_dataset(make_dataset(tmp / "ds", scenes=3, seqs=2))
        inbox = tmp / "inbox"
        for name, sigma in (("sharp", 0.6), ("blurry", 1.5), ("broken", 1.0)):
            blurred_submission(ds, inbox / name, sigma=sigma, method=name)
        m = json.loads((inbox / "broken" / "submission.json").read_text())
        m["timings"]["fit_s"] = -1
        (inbox / "broken" / "submission.json").write_text(json.dumps(m))
        yield ds.root, inbox, mp


def _board(tmp_path, made):
    """A fresh leaderboard root (the reported tables) and a copy of the inbox."""
    data, inbox, _ = made
    root = tmp_path / "leaderboard"
    shutil.copytree(ROOT / "leaderboard" / "reported", root / "reported")
    shutil.copytree(inbox, tmp_path / "inbox")
    return data, root, tmp_path / "inbox"


def _intake(data, root, inbox, *extra, check=2):
    # the test protocol's LPIPS, FID and FVD weights are not in the test's cache: scored without them
    return run_cli("leaderboard", "evaluate", str(inbox), "--root", str(root), "--data", str(data), "--quiet",
                   "--allow-missing", *extra, check=check)


def test_without_allow_missing_an_incomplete_score_is_one_line_and_not_filed(made, tmp_path):
    """The board files complete scores only: where the protocol's weights are missing, each
    submission is one line naming it and the missing metrics, nothing is filed, exit 2."""
    data, root, inbox = _board(tmp_path, made)
    shutil.rmtree(inbox / "broken")
    rc, out, err = run_cli("leaderboard", "evaluate", str(inbox), "--root", str(root), "--data", str(data),
                           "--quiet", check=2)
    lines = err.strip().splitlines()
    assert sorted(ln.split(":")[0] for ln in lines) == ["blurry", "sharp"], err
    assert all("cannot be computed here" in ln and "--allow-missing" in ln for ln in lines), err
    assert not (root / "results").exists() or not list((root / "results").iterdir())


def _assert_two_rows_and_one_error(root, inbox, out, err):
    assert sorted(p.name for p in (root / "results").iterdir()) == ["blurry.json", "sharp.json"]
    lines = err.strip().splitlines()
    assert lines == [f"broken: error: {inbox / 'broken' / 'submission.json'}: field 'timings.fit_s': expected a "
                     "number of seconds >= 0, got -1"], err
    assert "sharp: scored" in out and "blurry: scored" in out and "leaderboard regenerated" in out
    run_cli("leaderboard", "--root", str(root), "--check")


@pytest.mark.skipif(not HAVE_RAY, reason="Ray is not installed (pip install 'skyeyes-bench[ray]'; the dev extra, "
                    "and so CI, installs it)")
def test_an_inbox_on_ray_files_two_rows_and_names_the_malformed_one(made, tmp_path):
    from skyeyes_bench import ray_exec

    data, root, inbox = _board(tmp_path, made)
    with ray_exec.session(num_cpus=2):
        _, out, err = _intake(data, root, inbox, "--ray")
    _assert_two_rows_and_one_error(root, inbox, out, err)
    # the filed numbers are those `evaluate` gives in one process
    run_cli("evaluate", "--allow-missing", str(inbox / "sharp"), "--data", str(data), "--out", str(tmp_path / "one.json"), "--quiet")
    filed = json.loads((root / "results" / "sharp.json").read_text())
    assert scores(filed) == scores(json.loads((tmp_path / "one.json").read_text()))


def test_a_rerun_scores_only_what_changed_and_writes_only_root_and_out(made, tmp_path):
    data, root, inbox = _board(tmp_path, made)
    shas = {p.name: submission_sha(p) for p in inbox.iterdir()}
    _, out, err = _intake(data, root, inbox)
    _assert_two_rows_and_one_error(root, inbox, out, err)
    state = json.loads((tmp_path / "inbox.intake" / STATE_FILE).read_text())
    assert {k: v["sha256"] for k, v in state["submissions"].items()} == {k: shas[k] for k in ("sharp", "blurry")}
    # unchanged: skipped (the malformed one is reported again)
    _, out, err = _intake(data, root, inbox)
    assert "sharp: unchanged" in out and "blurry: unchanged" in out and "broken: error:" in err
    # fixed and changed: scored and filed (the changed one replaces the row the intake filed)
    m = json.loads((inbox / "broken" / "submission.json").read_text())
    m["timings"]["fit_s"] = 1.0
    (inbox / "broken" / "submission.json").write_text(json.dumps(m))
    frame = next((inbox / "sharp").rglob("*.png"))
    imagefiles.write_image(frame, np.zeros((32, 32, 3), np.float32))
    before = (root / "results" / "sharp.json").read_bytes()
    _, out, err = _intake(data, root, inbox, check=0)
    assert "broken: scored" in out and "sharp: scored" in out and "blurry: unchanged" in out and err == ""
    assert (root / "results" / "sharp.json").read_bytes() != before
    run_cli("leaderboard", "--root", str(root), "--check")
    # a row of that name filed from elsewhere is not replaced: that folder is one error line
    doc = json.loads((root / "results" / "blurry.json").read_text())
    doc["leaderboard"]["added_from"] = "/elsewhere/blurry.results.json"
    (root / "results" / "blurry.json").write_text(json.dumps(doc))
    imagefiles.write_image(next((inbox / "blurry").rglob("*.png")), np.ones((32, 32, 3), np.float32))
    _, out, err = _intake(data, root, inbox)
    assert err.startswith("blurry: error: ") and "already filed as 'blurry'" in err and err.count("\n") == 1
    assert json.loads((root / "results" / "blurry.json").read_text())["leaderboard"]["added_from"].startswith("/else")
    # written: the root, --out (INBOX.intake) and nothing else; the inbox only as this test changed it
    assert sorted(p.name for p in tmp_path.iterdir()) == ["inbox", "inbox.intake", "leaderboard"]
    assert sorted(p.name for p in inbox.iterdir()) == ["blurry", "broken", "sharp"]
