"""Issue 14: fuzz the readers at the edge (hypothesis, a bounded number of examples).

Each example takes a valid file (submission.json, dataset.json, scene.json, capture.json, a
results or partial file), replaces one field anywhere in it with an arbitrary JSON value (or
the whole file with arbitrary bytes), and runs the command that reads it. The command may
accept the input or refuse it with exit 2 and a one-line error; any other outcome (a
traceback, exit 1, a multi-line error for one bad field) fails.
"""

import json
import shutil

import pytest
from conftest import run_cli
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from builders.captures import make_carla
from builders.evaluation import blurred_submission, install_test_protocol, make_dataset

EXAMPLES = 40  # per reader; the default tier stays fast (about 1 s per reader here)

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(min_value=-(10**30), max_value=10**30)
    | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=12)
    | st.sampled_from(["..", "/", "a/../b", "\x00", "NaN", "", "0" * 70, "yaw000", "ground/000000.png"]),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=8), inner, max_size=5),
    max_leaves=12,
)


def _paths(doc, prefix=()):
    """Every path (tuple of keys/indices) to a value inside doc, the root included."""
    yield prefix
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _paths(v, (*prefix, i))


def _replace(doc, path, value):
    if not path:
        return value
    doc = json.loads(json.dumps(doc))
    d = doc
    for k in path[:-1]:
        d = d[k]
    d[path[-1]] = value
    return doc


@st.composite
def mutations(draw, doc):
    """(text of the file): one field replaced by an arbitrary value, or arbitrary bytes."""
    if draw(st.integers(0, 9)) == 0:
        return draw(st.binary(max_size=64))
    paths = list(_paths(doc))
    path = paths[draw(st.integers(0, len(paths) - 1))]
    return json.dumps(_replace(doc, path, draw(json_values))).encode()


def _assert_clean(rc, err):
    assert rc in (0, 2), err
    if rc == 2:
        lines = err.strip().splitlines()
        assert lines[0].startswith("skyeyes-bench: error: ") and "Traceback" not in err, err


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    base = tmp_path_factory.mktemp("fuzz")
    mp = pytest.MonkeyPatch()
    install_test_protocol(base, mp)
    mp.setenv("SKYEYES_CACHE", str(base / "cache"))
    from skyeyes_bench.data.layout import open_dataset
    from skyeyes_bench.evaluate import evaluate

    ds = open_dataset(make_dataset(base / "ds", scenes=2, seqs=1, frames=4))
    blurred_submission(ds, base / "sub", sigma=0.7)
    evaluate(base / "sub", data=base / "ds", out=base / "res.json", progress=False)
    evaluate(base / "sub", data=base / "ds", out=base / "p0.json", shard="0/2", progress=False)
    evaluate(base / "sub", data=base / "ds", out=base / "p1.json", shard="1/2", progress=False)
    make_carla(base / "carla")
    yield base
    mp.undo()


def _fuzz(world, tmp_path, target: str, argv, copy: str | None = None):
    """Run argv after each mutation of world/<target> (a copy of world/<copy> first, if given)."""
    work = tmp_path / "w"
    shutil.copytree(world, work, symlinks=True, ignore=shutil.ignore_patterns("cache"))
    file = work / target
    doc = json.loads(file.read_text())

    @settings(max_examples=EXAMPLES, deadline=None, database=None, derandomize=True,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
    @given(mutations(doc))
    def run(data):
        file.write_bytes(data)
        shutil.rmtree(work / "out", ignore_errors=True)
        for p in work.glob("out*"):
            p.unlink()
        rc, _, err = run_cli(*[a.replace("{w}", str(work)) for a in argv], check=None)
        _assert_clean(rc, err)

    run()


def test_fuzz_submission_manifest(world, tmp_path):
    _fuzz(world, tmp_path, "sub/submission.json", ["evaluate", "--allow-missing", "{w}/sub", "--data", "{w}/ds", "--quiet"])


def test_fuzz_dataset_json(world, tmp_path):
    _fuzz(world, tmp_path, "ds/dataset.json", ["data", "check", "{w}/ds"])


def test_fuzz_scene_json(world, tmp_path):
    _fuzz(world, tmp_path, "ds/test-0-lane00/scene.json", ["data", "check", "{w}/ds"])


def test_fuzz_carla_capture(world, tmp_path):
    _fuzz(world, tmp_path, "carla/capture.json", ["data", "import-carla", "{w}/carla", "{w}/out", "--no-progress"])


def test_fuzz_results_in_compare(world, tmp_path):
    _fuzz(world, tmp_path, "res.json", ["compare", "{w}/res.json", "{w}/res.json"])


def test_fuzz_partial_in_merge(world, tmp_path):
    _fuzz(world, tmp_path, "p0.json", ["merge", "{w}/p0.json", "{w}/p1.json", "--out", "{w}/out.json", "--quiet"])
