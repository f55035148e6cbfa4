"""The validation split of a protocol family (`protocols/<id>/val.toml`, `Protocol.val`): which
built-in protocols declare one, that it leaves every version's sha256 as filed, its one-line
errors (file and key), and how `protocols show` prints it."""

import json
import shutil
from pathlib import Path

import pytest
from conftest import ROOT, run_cli

from skyeyes_bench.errors import UserError
from skyeyes_bench.protocol import list_protocols, load_protocol

#: The sha256 each filed leaderboard row names for its protocol (the rows were scored before
#: val.toml existed: a validation split must not change them).
FILED = {"synthtown@4": ROOT / "leaderboard" / "results" / "skyeyes-synthtown4.json",
         "synthtown@3": ROOT / "leaderboard" / "results" / "skyeyes.json"}

GOOD_VAL = 'towns = ["val-0"]\nsource = "own"\nwhy = "a town of its own"\n'


def test_every_builtin_protocol_loads_and_says_its_validation_split():
    got = {p.ref: p.val for p in list_protocols(ROOT / "protocols")}
    assert set(got) == {"synthtown@1", "synthtown@2", "synthtown@3", "synthtown@4", "synthtown-stiff@1",
                        "carla-town04@1", "carla-town04@2", "carla-town04@3",
                        "citysample-region5@1", "citysample-region5@2", "citysample-region5@3"}
    for ref, val in got.items():
        family = ref.partition("@")[0]
        if family == "synthtown":
            assert (val.towns, val.source) == (("val-0",), "own"), ref
        elif family == "carla-town04":
            assert (val.towns, val.source) == (("Town05",), "train"), ref
        elif family == "citysample-region5":
            assert (val.towns, val.source) == (("region4",), "train"), ref
        else:  # a protocol for reporting only
            assert family == "synthtown-stiff" and val is None, ref
        if val is not None:
            assert val.why.strip(), ref


@pytest.mark.parametrize("ref", sorted(FILED))
def test_the_validation_split_leaves_the_filed_sha256(ref):
    filed = json.loads(FILED[ref].read_text())["protocol"]
    assert filed["ref"] == ref
    assert len(filed["sha256"]) == 64
    p = load_protocol(ref, ROOT / "protocols")
    assert p.val is not None
    assert p.sha256 == filed["sha256"]


@pytest.fixture
def root(tmp_path, monkeypatch) -> Path:
    """A private protocols folder (SKYEYES_PROTOCOLS) holding a copy of synthtown v4 and no val.toml."""
    r = tmp_path / "protocols"
    (r / "synthtown").mkdir(parents=True)
    shutil.copy(ROOT / "protocols" / "synthtown" / "v4.toml", r / "synthtown" / "v4.toml")
    monkeypatch.setenv("SKYEYES_PROTOCOLS", str(r))
    return r


def test_a_val_toml_is_read_for_every_version_and_not_hashed(root):
    bare = load_protocol("synthtown@4", root)
    assert bare.val is None
    (root / "synthtown" / "val.toml").write_text(GOOD_VAL)
    p = load_protocol("synthtown@4", root)
    assert (p.val.towns, p.val.source, p.val.why) == (("val-0",), "own", "a town of its own")
    assert p.sha256 == bare.sha256 and p == bare
    assert "val" not in p.to_dict()
    # another version of the family carries the same split
    shutil.copy(ROOT / "protocols" / "synthtown" / "v3.toml", root / "synthtown" / "v3.toml")
    assert load_protocol("synthtown@3", root).val.towns == ("val-0",)


#: name -> (val.toml text, what its one line must say beside the file)
BAD_VAL = {
    "a-test-town": ('towns = ["test-0"]\nsource = "own"\nwhy = "x"\n', ["key 'towns'", "test-0", "test town"]),
    "an-unknown-key": (GOOD_VAL + 'colour = "red"\n', ["unknown key 'val.colour'"]),
    "source-train-with-a-town-not-trained-on": ('towns = ["val-0"]\nsource = "train"\nwhy = "x"\n',
                                                ["key 'towns'", "train towns", 'source = "train"']),
    "source-own-with-a-train-town": ('towns = ["train-1"]\nsource = "own"\nwhy = "x"\n',
                                     ["key 'towns'", "train towns", 'source = "own"']),
    "no-town": ('towns = []\nsource = "own"\nwhy = "x"\n', ["key 'towns'", "at least one town"]),
    "an-unknown-source": ('towns = ["val-0"]\nsource = "elsewhere"\nwhy = "x"\n', ["key 'source'", "'elsewhere'"]),
    "no-why": ('towns = ["val-0"]\nsource = "own"\n', ["missing key 'val.why'"]),
    "towns-not-a-list": ('towns = "val-0"\nsource = "own"\nwhy = "x"\n', ["key 'val.towns'"]),
}


@pytest.mark.parametrize("case", sorted(BAD_VAL))
def test_a_bad_val_toml_is_one_line_naming_file_and_key(root, case):
    text, wants = BAD_VAL[case]
    f = root / "synthtown" / "val.toml"
    f.write_text(text)
    with pytest.raises(UserError) as e:
        load_protocol("synthtown@4", root)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{f}: "), msg
    for want in wants:
        assert want in msg, f"{want!r} not in: {msg}"
    # through the CLI: exit 2, one line on stderr, no traceback
    rc, out, err = run_cli("protocols", "show", "synthtown@4", check=2)
    assert err.count("\n") == 1 and str(f) in err and wants[0] in err and "Traceback" not in err


def test_protocols_show_prints_the_val_section():
    rc, out, err = run_cli("protocols", "show", "synthtown@4")
    lines = out.splitlines()
    assert "[val]" in lines
    section = lines[lines.index("[val]") + 1:]
    assert section[0] == 'towns = ["val-0"]'
    assert section[1] == 'source = "own"'
    assert section[2].startswith("why = ")
    # the hashed part is printed as before: the sha256 in the header is the filed one
    filed = json.loads(FILED["synthtown@4"].read_text())["protocol"]["sha256"]
    assert lines[0] == f"# synthtown@4  sha256 {filed}"
    rc, out, err = run_cli("protocols", "show", "synthtown@4", "--json")
    assert json.loads(out)["val"]["towns"] == ["val-0"]


def test_protocols_show_says_when_there_is_no_validation_split():
    rc, out, err = run_cli("protocols", "show", "synthtown-stiff")
    assert "[val]" not in out.splitlines()
    assert "no validation split" in out
    rc, out, err = run_cli("protocols", "show", "synthtown-stiff", "--json")
    assert json.loads(out)["val"] is None
