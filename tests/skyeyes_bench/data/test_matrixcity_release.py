"""import-matrixcity on a miniature MatrixCity download laid out as the public release ships it
(builders.matrixcity_release): raw and paper-split poses beside `transforms_origin.json`, packed
`.tar` files, depth in the sibling float16 and float32 trees; regions from aerial blocks; the
aerial pitch and altitude against the protocol."""

import json
import shutil

import numpy as np
import pytest
from builders.matrixcity_release import FAR_CM, make_release
from conftest import run_cli

from skyeyes_bench import imagefiles
from skyeyes_bench.data.importers import matrixcity_depth_to_metres
from skyeyes_bench.data.layout import open_dataset

REGIONS = ("--region", "region1=block_1", "--region", "region5=block_2")
DENSE = ("--include", "aerial/*/*/transforms.json", "--include", "street/train_dense/*/transforms.json")


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    root = tmp_path_factory.mktemp("dl") / "MatrixCity"
    return root, make_release(root)


def _import(src, out, *args, check=0):
    return run_cli("data", "import-matrixcity", str(src), str(out), "--no-progress", *args, check=check)


def _frames_by_image(ds):
    """{source image path: (kind, frame)} through the pixels: every imported frame is matched to the
    source image with the same pixels (random, so unique)."""
    return [(kind, fr) for s in ds.scenes.values() for kind, frs in (("ground", s.ground), ("aerial", s.aerial))
            for fr in frs]


def _match(truth_paths, fr):
    px = imagefiles.read_image_uint8(fr.path)
    hits = [p for p in truth_paths if np.array_equal(imagefiles.read_image_uint8(p), px)]
    assert len(hits) == 1, (fr.path, hits)
    return hits[0]


def test_release_raw_regions_and_depth_trees(release, tmp_path):
    root, truth = release
    out = tmp_path / "out"
    _, stdout, _ = _import(root, out, "--pose-format", "raw", *DENSE, *REGIONS)  # SRC: the download's root
    ds = open_dataset(out, check_pixels=True)
    assert ds.splits == {"train": ("region1-lane00",), "test": ("region5-lane00",)}
    h, v = ds.scenes["region1-lane00"], ds.scenes["region5-lane00"]
    # 1 m dense captures resampled to 2 m: road H x = 0, 2, 4, 6; road V y = 0, 2, 4
    np.testing.assert_allclose([f.camera().center[0] for f in h.sequences["yaw000"]], [0, 2, 4, 6], atol=1e-4)
    np.testing.assert_allclose([f.camera().center[1] for f in v.sequences["yaw000"]], [0, 2, 4], atol=1e-4)
    assert list(h.sequences) == ["yaw000", "yaw090", "yaw180", "yaw270"]
    assert len(h.aerial) == 4 and len(v.aerial) == 2  # block_1 (3) + block_1_test (1); block_2 (2)
    meta = ds.meta
    assert meta["regions"] == {"region1": ["block_1"], "region5": ["block_2"]}
    assert meta["depth_roots"] == [str((root / n).resolve()) for n in ("small_city_depth_float32", "small_city_depth")]
    assert meta["aerial_pitch_deg"] == [-45.0, -45.0] and meta["aerial_altitude_m"] == [100.0, 100.0]
    diffs = " | ".join(meta["protocol_differences"])
    assert "aerial pitch" not in diffs and "aerial altitude" not in diffs
    # the down faces were never in transforms.json (only in transforms_origin.json); up faces are left out
    assert "non-horizontal street frames" in diffs
    streets = list(truth["street"])
    for fr in [*h.ground, *v.ground]:
        src = _match(streets, fr)
        np.testing.assert_allclose(fr.c2w, truth["street"][src], atol=1e-5)
        np.testing.assert_array_equal(fr.depth(), truth["street_depth_m"][src])  # float16 tree: 65504 is sky
        assert np.isinf(fr.depth()[0, 1])
    aerials = list(truth["aerial"])
    for fr in [*h.aerial, *v.aerial]:
        src = _match(aerials, fr)
        np.testing.assert_allclose(fr.c2w, truth["aerial"][src], atol=1e-5)
        d = fr.depth()  # from the float32 tree: 655.04 m and 700 m are depths, not sky
        np.testing.assert_allclose(d, truth["aerial_depth_m"][src], rtol=1e-6)
        assert d[0, 1] == pytest.approx(655.04) and d[1, 1] == pytest.approx(FAR_CM / 100)
    assert "differs from the protocol" in stdout


def test_release_paper_split_skips_transforms_origin(release, tmp_path):
    """`transforms_origin.json` (raw layout) also matches transforms_*.json: --pose-format paper
    on the whole download must read only the pose/ splits."""
    root, truth = release
    out = tmp_path / "out"
    _import(root / "small_city", out, "--pose-format", "paper", *REGIONS)
    ds = open_dataset(out)
    assert ds.meta["pose_format"] == "paper"
    h, v = ds.scenes["region1-lane00"], ds.scenes["region5-lane00"]
    np.testing.assert_allclose([f.camera().center[0] for f in h.sequences["yaw090"]], [0, 2, 4, 6], atol=1e-4)
    assert len(h.aerial) == 4 and len(v.aerial) == 2
    for fr in h.aerial:
        np.testing.assert_allclose(fr.c2w, truth["aerial"][_match(list(truth["aerial"]), fr)], atol=1e-5)


def test_release_all_sets_resampled_per_block(release, tmp_path):
    """A download holds 5 m (`train`) and 1 m (`train_dense`) street blocks: each is resampled on its own."""
    root, _ = release
    out = tmp_path / "out"
    _import(root, out, "--town", "region5")
    meta = open_dataset(out).meta
    diffs = meta["protocol_differences"]
    assert "ground step resampled from 1.00 m to 2.00 m (one capture point in 2)" in diffs
    assert "ground step 5.00 m kept (no whole number of source steps makes 2 m)" in diffs
    assert meta["step_m"] == [2.0, 5.0]
    steps = ds_steps = {b.split("/")[-1]: s for b, s in meta["block_steps_m"].items()}
    assert ds_steps == steps and steps["small_city_road_horizon"] == pytest.approx(5.0)


def test_aerial_pitch_and_altitude_against_protocol(tmp_path):
    root = tmp_path / "MatrixCity"
    make_release(root, aerial_height=150.0, aerial_pitch=-60.0)
    out = tmp_path / "out"
    _import(root / "small_city", out, "--pose-format", "raw", "--town", "region5")
    meta = open_dataset(out).meta
    assert meta["aerial_pitch_deg"] == [-60.0, -60.0] and meta["aerial_altitude_m"] == [150.0, 150.0]
    assert "aerial pitch -60.0..-60.0 deg (protocol: -45)" in meta["protocol_differences"]
    assert ("aerial altitude 150.0..150.0 m above the ground under the street cameras (protocol: 100)"
            in meta["protocol_differences"])


def test_paper_split_with_origin_files_beside(release, tmp_path):
    """The defect alone: --pose-format paper on a map folder that holds transforms_origin.json."""
    root, _ = release
    _import(root / "small_city", tmp_path / "out", "--pose-format", "paper", "--town", "region5")
    assert open_dataset(tmp_path / "out").meta["pose_format"] == "paper"


def test_float32_depth_tree_keeps_far_depths(release, tmp_path):
    """The defect alone: a float32 depth of 700 m (beyond float16's 65504 cm) is a depth, not sky."""
    root, truth = release
    _import(root / "small_city", tmp_path / "out", "--pose-format", "raw", "--town", "region5",
            "--depth-root", str(root / "small_city_depth_float32"))
    aerial = [fr for s in open_dataset(tmp_path / "out").scenes.values() for fr in s.aerial]
    assert aerial
    for fr in aerial:
        assert fr.depth()[1, 1] == pytest.approx(FAR_CM / 100) and fr.depth()[0, 1] == pytest.approx(655.04)


def test_release_packed_and_nested_images(release, tmp_path):
    root = tmp_path / "MatrixCity"
    shutil.copytree(release[0], root)
    block = root / "small_city" / "aerial" / "train" / "block_2"
    nested = block / "block_2"  # the tar unpacked into the block's own folder
    nested.mkdir()
    for png in block.glob("*.png"):
        png.rename(nested / png.name)
    _import(root, tmp_path / "ok", "--pose-format", "raw", *DENSE, *REGIONS)
    assert len(open_dataset(tmp_path / "ok").scenes["region5-lane00"].aerial) == 2
    shutil.rmtree(nested)  # still packed: the error names the tar
    _, _, err = _import(root, tmp_path / "bad", "--pose-format", "raw", *DENSE, *REGIONS, check=2)
    assert f"frames[0].frame_index: image {block / '0000.png'} not found (unpack {block}.tar into {block.parent} first)" in err
    assert err.count("\n") == 1


def test_release_refusals(release, tmp_path):
    root, _ = release
    _, _, err = _import(root, tmp_path / "o", *REGIONS[:2], "--region", "region5=block_9", check=2)
    assert "--region region5=block_9: no aerial block 'block_9' in SRC (aerial blocks: block_1, block_1_test, block_2)" in err
    _, _, err = _import(root, tmp_path / "o", "--region", "region5", check=2)
    assert "--region 'region5': expected TOWN=BLOCK[,BLOCK...]" in err
    two = tmp_path / "two"
    (two / "big_city" / "aerial" / "train" / "b").mkdir(parents=True)
    (two / "big_city" / "aerial" / "train" / "b" / "transforms.json").write_text(json.dumps({"frames": []}))
    shutil.copytree(root / "small_city", two / "small_city")
    _, _, err = _import(two, tmp_path / "o", check=2)
    assert f"{two}: holds several MatrixCity maps (big_city, small_city); pass one as SRC" in err


def test_depth_mask_only_float16():
    cm = np.array([[100.0, 65504.0, FAR_CM, 0.0, np.nan]])
    np.testing.assert_array_equal(matrixcity_depth_to_metres(cm, half=True),
                                  np.float32([[1.0, np.inf, np.inf, np.inf, np.inf]]))
    np.testing.assert_array_equal(matrixcity_depth_to_metres(cm, half=False),
                                  np.float32([[1.0, 655.04, 700.0, np.inf, np.inf]]))
