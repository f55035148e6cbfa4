"""Messages and exit codes a user meets (issue 58): every --help renders; `protocols show` prints
"∞"; a submission.json naming an unknown protocol says which file; `evaluate` exits 2 when a metric
its protocol requires cannot be computed, unless --allow-missing; --json on every command that
prints a result; `compare` says nothing about a features sidecar that is not there, and draws
its progress only on a terminal."""

import argparse
import json
import shutil
import tomllib

import pytest
from builders.evaluation import (ROOT, TEST_PROTOCOL, blurred_submission, install_test_protocol, make_dataset,
                                 protocol_env)
from conftest import run_cli

from skyeyes_bench import paths
from skyeyes_bench.cli import build_parser
from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.results import features_path
from skyeyes_bench.submission import write_template


def _parsers():
    """(command words, parser) for the top-level parser and every subcommand and action under it."""
    def walk(p, words):
        yield words, p
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, sp in a.choices.items():
                    yield from walk(sp, [*words, name])
    return list(walk(build_parser(), []))


def test_every_help_renders():
    """argparse %-formats help strings but not descriptions: a description's "%%" printed as is."""
    found = _parsers()
    assert len(found) > 20 and ["compare"] in [w for w, _ in found]
    for words, p in found:
        text = p.format_help()
        for bad in ("%%", "%(", "\\u"):
            assert bad not in text, (words, bad, [line for line in text.splitlines() if bad in line])
        rc, out, err = run_cli(*words, "--help")  # exit 0, the help on stdout
        assert out.startswith("usage: ") and err == "", words


def test_compare_help_says_95_percent():
    rc, out, err = run_cli("compare", "--help")
    assert "95% HDI" in out


def test_protocols_show_prints_infinity_not_an_escape():
    want = tomllib.loads((ROOT / "protocols" / "synthtown" / "v4.toml").read_text())
    assert "∞" in want["title"]
    rc, out, err = run_cli("protocols", "show", "synthtown@4")
    assert "\\u" not in out and f"title = {json.dumps(want['title'], ensure_ascii=False)}" in out
    assert "FID∞" in out
    rc, out, err = run_cli("protocols", "show", "synthtown@4", "--json")
    assert "\\u" not in out and json.loads(out)["title"] == want["title"]


def test_protocols_list_json_is_the_list():
    rc, text, _ = run_cli("protocols", "list")
    rc, out, _ = run_cli("protocols", "list", "--json")
    rows = json.loads(out)
    assert [f"{r['ref']}\t{r['title']}" for r in rows] == text.splitlines()
    assert all(len(r["sha256"]) == 64 for r in rows)


# --------------------------------------------------------------------------- a tiny world


#: evaltest@1 without LPIPS and with clips longer than any sequence: FVD and KVD turn out
#: unavailable only once scored ("0 clips"), nothing is missing up front.
LONG_CLIPS = (TEST_PROTOCOL.replace('id = "evaltest"', 'id = "evallong"')
              .replace('[metrics.lpips]\naggregate = "mean"\nextractor = "lpips-alex-v0.1"\n', "")
              .replace("clip_length = 4", "clip_length = 32"))


@pytest.fixture(scope="module")
def w(tmp_path_factory):
    """A dataset of 3 scenes x 2 sequences x 8 frames (6 sequences: intervals), a blurred
    submission and a sharper one, scored with --allow-missing (no LPIPS weights in tests)."""
    tmp = tmp_path_factory.mktemp("msg")
    assert "lpips" not in LONG_CLIPS and "clip_length = 32" in LONG_CLIPS
    with protocol_env(tmp) as mp:
        install_test_protocol(tmp, mp, LONG_CLIPS)
        ds = open_dataset(make_dataset(tmp / "ds", scenes=3, frames=8))
        for name, sigma in (("a", 0.7), ("b", 1.5)):
            blurred_submission(ds, tmp / name, sigma=sigma, method=name)
            run_cli("evaluate", str(tmp / name), "--data", str(ds.root), "--out", str(tmp / f"{name}.json"),
                    "--quiet", "--allow-missing")
        yield tmp


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_unknown_protocol_in_submission_json_names_the_file(w, tmp_path):
    sub = tmp_path / "sub"
    shutil.copytree(w / "a", sub)
    man = json.loads((sub / "submission.json").read_text())
    man["protocol"] = "evaltest@9"
    (sub / "submission.json").write_text(json.dumps(man))
    rc, out, err = run_cli("evaluate", str(sub), "--data", str(w / "ds"), "--out", str(tmp_path / "r.json"), check=2)
    line = _one_line(err)
    assert f"{sub / 'submission.json'}: field 'protocol'" in line and "no version 9" in line, line
    # a results file naming one: compare says which file too
    doc = json.loads((w / "a.json").read_text())
    doc["protocol"]["ref"] = "evaltest@9"
    for n in ("x", "y"):
        (tmp_path / f"{n}.json").write_text(json.dumps(doc))
    rc, out, err = run_cli("compare", str(tmp_path / "x.json"), str(tmp_path / "y.json"), check=2)
    line = _one_line(err)
    assert f"{tmp_path / 'x.json'}: field 'protocol.ref'" in line and "no version 9" in line, line


def test_evaluate_exits_2_when_a_required_metric_cannot_be_computed(w, tmp_path):
    """evaltest@1 requires LPIPS, whose weights this test's cache lacks: exit 2 before any scoring
    (no feature computed, nothing written), one line naming it and the flag; --allow-missing:
    exit 0 and the partial results as before. The Python API is strict likewise."""
    import skyeyes_bench as sb
    from skyeyes_bench.evaluate import MissingMetrics

    out = tmp_path / "r.json"
    rc, text, err = run_cli("evaluate", str(w / "a"), "--data", str(w / "ds"), "--out", str(out), check=2)
    line = _one_line(err)
    assert "requires lpips" in line and "--allow-missing" in line and "weights fetch" in line, line
    assert text == "" and not out.exists() and not features_path(out).exists()
    assert not paths.features_dir().exists() or not any(paths.features_dir().rglob("*.f64"))  # nothing scored
    with pytest.raises(MissingMetrics, match="requires lpips") as e:
        sb.evaluate(w / "a", w / "ds")
    assert list(e.value.missing) == ["lpips"]
    # several submissions: one line each, exit 2
    rc, text, err = run_cli("evaluate", str(w / "a"), str(w / "b"), "--data", str(w / "ds"), check=2)
    assert len(err.strip().splitlines()) == 2 and err.count("requires lpips") == 2, err
    assert not (w / "a.results.json").exists()
    # partial scores on request
    rc, text, err = run_cli("evaluate", str(w / "a"), "--data", str(w / "ds"), "--out", str(out), "--quiet",
                            "--allow-missing")
    res = json.loads(out.read_text())
    assert res["metrics"]["lpips"]["status"] == "unavailable" and res["metrics"]["fid"]["status"] == "ok"
    assert "lpips  unavailable" in text


def test_evaluate_exits_2_for_a_metric_found_unavailable_while_scoring(w, tmp_path):
    """evallong@1 asks for clips of 32 frames of 8-frame sequences: FVD/KVD have no clip, which
    only the scoring finds; exit 2 naming both, nothing written."""
    ds = make_dataset(tmp_path / "ds", protocol="evallong@1", name="evallong", scenes=1, frames=8)
    sub = blurred_submission(open_dataset(ds), tmp_path / "sub")
    out = tmp_path / "r.json"
    rc, text, err = run_cli("evaluate", str(sub), "--data", str(ds), "--out", str(out), "--quiet", check=2)
    line = _one_line(err)
    assert "requires fvd, kvd" in line and "0 clips" in line, line
    assert not out.exists() and not features_path(out).exists()
    run_cli("evaluate", str(sub), "--data", str(ds), "--out", str(out), "--quiet", "--allow-missing")
    assert json.loads(out.read_text())["metrics"]["fvd"]["status"] == "unavailable"


def test_json_on_every_command_that_prints_a_result(w, tmp_path):
    rc, out, _ = run_cli("evaluate", str(w / "a"), "--data", str(w / "ds"), "--out", str(tmp_path / "e.json"),
                         "--quiet", "--allow-missing", "--json")
    assert json.loads(out)["metrics"] == json.loads((tmp_path / "e.json").read_text())["metrics"]
    for i in (0, 1):
        run_cli("evaluate", str(w / "a"), "--data", str(w / "ds"), "--out", str(tmp_path / f"p{i}.json"),
                "--shard", f"{i}/2", "--quiet", "--allow-missing")
    rc, out, _ = run_cli("merge", str(tmp_path / "p0.json"), str(tmp_path / "p1.json"), "--out",
                         str(tmp_path / "m.json"), "--quiet", "--json")
    assert json.loads(out)["metrics"] == json.loads((tmp_path / "m.json").read_text())["metrics"]
    rc, out, _ = run_cli("data", "check", str(w / "ds"), "--json")
    assert json.loads(out)["name"] == "evaltiny"
    rc, out, _ = run_cli("weights", "status", "--json")
    assert "extractors" in json.loads(out)
    rc, out, _ = run_cli("compare", str(w / "a.json"), str(w / "b.json"), "--json")
    assert json.loads(out)["a"] == "a"


def _about_sidecars(err: str) -> list[str]:
    """The lines of `err` about features sidecars (the test protocol's short emcee chains add
    convergence warnings of their own)."""
    return [line for line in err.splitlines() if "sidecar" in line or ".npz" in line]


def test_compare_says_nothing_about_a_sidecar_that_is_not_there(w, tmp_path):
    """A results file filed without its sidecar (as on the leaderboard: renamed, `features.file`
    naming a file that is not beside it): its stored replicates serve and nothing is said. An
    older file without replicates: its set metrics are skipped with the reason, still no warning.
    A sidecar that is there but damaged: one warning."""
    for n in ("a", "b"):
        shutil.copy(w / f"{n}.json", tmp_path / f"row-{n}.json")
    rows = [str(tmp_path / f"row-{n}.json") for n in ("a", "b")]
    rc, out, err = run_cli("compare", *rows)
    assert _about_sidecars(err) == [], err
    assert "fid    A" in out and "skipped" not in out.replace("lpips  skipped", "")
    # older files: no replicates, no sidecar
    for r in rows:
        doc = json.loads(open(r).read())
        for m in ("fid", "kid", "fvd", "kvd"):
            del doc["metrics"][m]["replicates"]
        open(r, "w").write(json.dumps(doc))
    rc, out, err = run_cli("compare", *rows)
    assert _about_sidecars(err) == [], err
    assert "fid    skipped: no replicates of the same resampling in the results and no features sidecars" in out
    # ... with their sidecars, one of them damaged
    for n in ("a", "b"):
        name = json.loads((w / f"{n}.json").read_text())["features"]["file"]
        shutil.copy(w / name, tmp_path / name)
    side = tmp_path / json.loads((w / "b.json").read_text())["features"]["file"]
    side.write_bytes(side.read_bytes()[:-1] + b"!")
    rc, out, err = run_cli("compare", *rows)
    said = _about_sidecars(err)
    assert len(said) == 1 and said[0].startswith("skyeyes-bench: warning: ") and "sha256 differs" in said[0], err


def test_compare_progress_only_on_a_terminal(w, monkeypatch):
    from skyeyes_bench import comparison

    monkeypatch.setattr(comparison, "PROGRESS_DELAY_S", 0.0)  # the bar waits 2 s; these run faster
    rc, out, err = run_cli("compare", str(w / "a.json"), str(w / "b.json"), tty=True)
    assert "compare:" in err and "metric" in err
    rc, out, err = run_cli("compare", str(w / "a.json"), str(w / "b.json"))
    assert "compare:" not in err and "\r" not in err, err
