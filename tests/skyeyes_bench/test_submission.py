"""Submission format: writer, template, and validation of every malformed case (all at once,
precise messages, nothing written)."""

import json
import os
import shutil
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli
from builders.evaluation import blurred_submission, install_test_protocol, make_dataset

from skyeyes_bench import imagefiles
from skyeyes_bench.data.layout import open_dataset
from skyeyes_bench.errors import UserError
from skyeyes_bench.submission import SubmissionWriter, expected_frames, read_submission


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("ds") / "evaltiny")


@pytest.fixture
def proto(tmp_path, monkeypatch):
    return install_test_protocol(tmp_path, monkeypatch)


def test_writer_layout_and_manifest(tiny, proto, tmp_path):
    ds = open_dataset(tiny)
    sub = blurred_submission(ds, tmp_path / "sub")
    frames = expected_frames(ds)
    assert len(frames) == 2 * 2 * 16
    scene, f = frames[5]
    p = sub / scene / f.file
    assert p.is_file() and f.file.startswith("ground/")
    assert imagefiles.image_header(p)[:3] == (32, 32, 3)
    m = read_submission(sub)
    assert m["protocol"] == "evaltest@1" and m["dataset"]["name"] == "evaltiny" and m["method"] == "blur"
    assert m["timings"]["fit_s"] == 1.0 and m["hardware"]["cores"] == os.cpu_count()
    assert len(m["protocol_sha256"]) == 64


def test_writer_is_atomic_and_checks(tiny, proto, tmp_path):
    ds = open_dataset(tiny)
    scene, f = expected_frames(ds)[0]
    out = tmp_path / "sub"
    with pytest.raises(UserError, match="frames not added"):
        with SubmissionWriter(out, dataset=ds, method="m") as w:
            w.add(scene, f, np.zeros((32, 32, 3)))
            w.finish()
    assert not out.exists() and not list(tmp_path.glob(".sub*"))
    with pytest.raises(UserError, match="image is 16x16, the camera is 32x32"):
        with SubmissionWriter(out, dataset=ds, method="m") as w:
            w.add(scene, f, np.zeros((16, 16, 3)))
    with pytest.raises(RuntimeError, match="SubmissionWriter closed without finish"):
        with SubmissionWriter(out, dataset=ds, method="m"):
            pass
    assert not out.exists() and not list(tmp_path.glob(".sub*"))
    train = ds.scenes["train-0-lane00"].ground[0]
    with pytest.raises(UserError, match="not a ground frame of a test scene"):
        with SubmissionWriter(out, dataset=ds, method="m") as w:
            w.add("train-0-lane00", train, np.zeros((32, 32, 3)))
    assert not out.exists()


def test_template_cli(tiny, proto, tmp_path):
    run_cli("submission", "template", "--data", str(tiny), "--out", str(tmp_path / "skel"))
    lines = [ln for ln in (tmp_path / "skel" / "EXPECTED_FRAMES.txt").read_text().splitlines()
             if not ln.startswith("#")]
    assert len(lines) == 64 and lines[0].split("\t")[:2] == ["test-0-lane00/ground/000000.png", "32x32"]
    assert json.loads((tmp_path / "skel" / "submission.json").read_text())["protocol"] == "evaltest@1"
    run_cli("submission", "template", "--data", str(tiny), "--out", str(tmp_path / "gt"), "--from-ground-truth")
    s, f = expected_frames(open_dataset(tiny))[7]
    assert (tmp_path / "gt" / s / f.file).read_bytes() == f.path.read_bytes()
    rc, _, err = run_cli("submission", "template", "--data", str(tiny), "--out", str(tmp_path / "gt"), check=2)
    assert "already exists" in err


def _png_with_size(path, w, h):
    """A PNG whose header claims w x h (a decompression bomb's header)."""
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    chunk = lambda t, d: struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d))  # noqa: E731
    idat = zlib.compress(b"\x00" * 10)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b""))


def test_every_malformed_case_listed_at_once_and_nothing_written(tiny, proto, tmp_path):
    ds = open_dataset(tiny)
    sub = tmp_path / "sub"
    shutil.copytree(blurred_submission(ds, tmp_path / "good"), sub)
    fr = [sub / s / f.file for s, f in expected_frames(ds)]
    fr[0].unlink()  # missing
    (sub / "test-0-lane00" / "ground" / "999999.png").write_bytes(fr[1].read_bytes())  # extra
    imagefiles.write_image(fr[2], np.zeros((16, 16, 3)))  # wrong size
    fr[3].write_bytes(fr[3].read_bytes()[:200])  # truncated
    imagefiles.write_image(fr[4], np.zeros((32, 32)))  # grey: not RGB
    outside = tmp_path / "outside.png"
    shutil.copyfile(fr[5], outside)
    fr[5].unlink()
    fr[5].symlink_to(outside)  # symlink leaving the folder
    _png_with_size(fr[6], 100_000, 100_000)  # decompression bomb
    fr[7].write_bytes(b"GIF89a not a png")  # not a PNG
    out = tmp_path / "res.json"
    rc, _, err = run_cli("evaluate", "--allow-missing", str(sub), "--data", str(tiny), "--out", str(out), "--quiet", check=2)
    assert "8 problems" in err
    assert "1 expected frame(s) missing: test-0-lane00/ground/000000.png" in err
    assert "999999.png: extra file" in err
    assert "image is 16x16, expected 32x32" in err
    assert f"{fr[3]}: cannot decode image" in err
    assert f"{fr[4]}: expected an RGB image (PNG colour type 2), got grey" in err
    assert f"{fr[5]}: symlink leaves the submission folder" in err
    assert "absurd image size 100000x100000" in err
    assert f"{fr[7]}: not a PNG file" in err
    assert not out.exists() and not list(tmp_path.glob("*.npz")) and not list(tmp_path.glob(".res*"))


def test_protocol_and_manifest_mismatch(tiny, proto, tmp_path):
    ds = open_dataset(tiny)
    sub = blurred_submission(ds, tmp_path / "sub")
    m = json.loads((sub / "submission.json").read_text())
    m["protocol"] = "synthtown@1"
    (sub / "submission.json").write_text(json.dumps(m))
    rc, _, err = run_cli("evaluate", "--allow-missing", str(sub), "--data", str(tiny), "--quiet", check=2)
    assert "dataset is for protocol 'evaltest@1', the submission for 'synthtown@1'" in err
    m["protocol"] = "evaltest@1"
    m["protocol_sha256"] = "0" * 64
    (sub / "submission.json").write_text(json.dumps(m))
    rc, _, err = run_cli("evaluate", "--allow-missing", str(sub), "--data", str(tiny), "--quiet", check=2)
    assert "field 'protocol_sha256' does not match" in err
    del m["method"]
    (sub / "submission.json").write_text(json.dumps(m))
    rc, _, err = run_cli("evaluate", "--allow-missing", str(sub), "--data", str(tiny), "--quiet", check=2)
    assert "field 'method': missing (expected the method's name" in err
    assert not list(tmp_path.glob("*.results.json"))


def test_missing_dataset_names_the_command(tmp_path, monkeypatch):
    from skyeyes_bench.evaluate import resolve_data
    from skyeyes_bench.protocol import load_protocol

    with pytest.raises(UserError, match=r"skyeyes-bench data synthtown --preset small"):
        resolve_data({"dataset": {"name": "synthtown-small"}}, load_protocol("synthtown@1"), None)


def _tree(root):
    """{relative path: bytes, a link's target, or None for a folder} of everything under `root` (links not followed)."""
    out = {}
    for folder, dirs, files in os.walk(root):
        for name in dirs + files:
            p = Path(folder) / name
            out[str(p.relative_to(root))] = (os.readlink(p) if p.is_symlink() else None if p.is_dir() else p.read_bytes())
    return out


@pytest.mark.parametrize("where", ["sub/new", "sub/test-0-lane00/ground/new", "link/new", "sub/test-0-lane00"])
@pytest.mark.parametrize("extra", [(), ("--force",), ("--from-ground-truth",), ("--force", "--from-ground-truth")])
def test_template_out_inside_another_submission_is_refused(tiny, proto, tmp_path, where, extra):
    """--out in a folder of which a parent holds a submission.json would spoil that submission (evaluate
    then finds extra files in it): one line naming it, exit 2, nothing written, with or without --force."""
    sub = tmp_path / "sub"
    run_cli("submission", "template", "--data", str(tiny), "--out", str(sub), "--from-ground-truth")
    (tmp_path / "link").symlink_to(sub)
    before = _tree(tmp_path)
    out = tmp_path / where
    rc, stdout, err = run_cli("submission", "template", "--data", str(tiny), "--out", str(out), *extra, check=2)
    assert stdout == "" and err.count("\n") == 1, err
    assert err.startswith(f"skyeyes-bench: error: {out}: lies inside the submission {sub} "), err
    assert _tree(tmp_path) == before
    # the same for a method writing its submission
    with pytest.raises(UserError, match=f"lies inside the submission {sub} "):
        SubmissionWriter(out, dataset=open_dataset(tiny), method="m", overwrite="--force" in extra)
    assert _tree(tmp_path) == before


def test_template_out_beside_or_over_a_submission(tiny, proto, tmp_path):
    """A sibling of a submission is fine; the submission itself is replaced only with --force (and
    only because it is a submission), as before."""
    sub = tmp_path / "sub"
    run_cli("submission", "template", "--data", str(tiny), "--out", str(sub), "--from-ground-truth")
    run_cli("submission", "template", "--data", str(tiny), "--out", str(tmp_path / "sub2"))
    before = _tree(sub)
    rc, _, err = run_cli("submission", "template", "--data", str(tiny), "--out", str(sub), check=2)
    assert err.strip() == f"skyeyes-bench: error: {sub}: already exists; pass --force to replace it"
    assert _tree(sub) == before
    run_cli("submission", "template", "--data", str(tiny), "--out", str(sub), "--force")
    assert sorted(p.name for p in sub.iterdir()) == ["EXPECTED_FRAMES.txt", "submission.json"]
