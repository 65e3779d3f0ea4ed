"""Dataset loaders (Blender, nerfstudio) and joining weight stacks to frames."""

import json
import math

import numpy as np
import pytest
from PIL import Image

from nerf_stage.cli import main
from nerf_stage.data.dataset import join_weights, load_dataset
from palette_core import InputError, WeightStack, read_stack
from palette_core.basis import weights_to_rgb

from .helpers import expect_error, llff_capture, png_header_only

POSE = [[1, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]


def write_png(path, rgba):
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(rgba, np.uint8)).save(path)


def blender_folder(root, splits=(("train", 2), ("test", 1)), size=(6, 4)):
    """Hand-written Blender layout: half-transparent red images, file_path without suffix."""
    w, h = size
    for split, n in splits:
        frames = []
        for i in range(n):
            write_png(root / split / f"r_{i}.png", np.tile([255, 0, 0, 128], (h, w, 1)))
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": POSE})
        (root / f"transforms_{split}.json").write_text(
            json.dumps({"camera_angle_x": 0.6, "frames": frames}))
    return root


def test_blender_layout(tmp_path):
    data = load_dataset(blender_folder(tmp_path), background=(0, 0, 1))
    assert data.names == ["train/r_0.png", "train/r_1.png", "test/r_0.png"]
    assert data.splits == ["train", "train", "test"]
    assert data.indices("test").tolist() == [2]
    assert data.poses.shape == (3, 4, 4) and np.allclose(data.poses[0], POSE)
    k = data.intrinsics
    assert (k.width, k.height, k.cx, k.cy) == (6, 4, 3, 2)
    assert k.fx == k.fy == pytest.approx(0.5 * 6 / math.tan(0.3))
    a = 128 / 255
    assert np.allclose(data.alpha, a)
    assert np.allclose(data.images[0, 0, 0], [a, 0, 1 - a], atol=1e-6)  # red over blue


def test_nerfstudio_layout(tmp_path):
    frames = []
    for i in range(9):
        write_png(tmp_path / "images" / f"frame_{i:03d}.png", np.full((4, 6, 3), 100))
        frames.append({"file_path": f"images/frame_{i:03d}.png", "transform_matrix": POSE[:3]})
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"fl_x": 5.0, "fl_y": 6.0, "cx": 3.1, "cy": 1.9, "w": 6, "h": 4, "frames": frames}))
    data = load_dataset(tmp_path)
    k = data.intrinsics
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (5, 6, 3.1, 1.9, 6, 4)
    assert data.indices("test").tolist() == [7] and len(data.indices("train")) == 8
    assert np.allclose(data.poses[0], POSE) and np.all(data.alpha == 1)


def nerfstudio_folder(root, n=4, **fields):
    frames = []
    for i in range(n):
        write_png(root / "images" / f"f{i}.png", np.full((4, 6, 3), 100))
        frames.append({"file_path": f"images/f{i}.png", "transform_matrix": POSE})
    (root / "transforms.json").write_text(json.dumps(
        {"fl_x": 5.0, "fl_y": 5.0, "cx": 3, "cy": 2, "w": 6, "h": 4, "frames": frames,
         **fields}))
    return root


def test_nerfstudio_split_lists(tmp_path):
    lists = {"train_filenames": ["images/f0.png", "./images/f2.png"],
             "val_filenames": ["images/f1.png"], "test_filenames": ["images/f3.png"]}
    data = load_dataset(nerfstudio_folder(tmp_path, **lists))
    assert data.splits == ["train", "val", "train", "test"]
    lists["train_filenames"].append("images/f1.png")
    lists["val_filenames"] = lists["test_filenames"]  # held out for nerfstudio's both
    data = load_dataset(nerfstudio_folder(tmp_path / "again", **lists))
    assert data.splits == ["train", "train", "train", "test"]


@pytest.mark.parametrize("lists, message", [
    ({"train_filenames": ["images/f0.png", "images/f1.png"], "test_filenames": ["images/f2.png"]},
     "in no split list: images/f3.png"),
    ({"train_filenames": ["images/f0.png", "images/f1.png", "images/f2.png", "images/f3.png"],
      "test_filenames": ["images/f3.png"]}, "listed in two splits"),
    ({"train_filenames": "images/f0.png"}, "must be a list"),
])
def test_bad_nerfstudio_split_lists(tmp_path, lists, message):
    with pytest.raises(InputError, match=message):
        load_dataset(nerfstudio_folder(tmp_path, **lists))


def test_nerfstudio_frames_may_carry_their_own_cameras(tmp_path):
    frames = []
    for i in range(3):
        write_png(tmp_path / "images" / f"frame_{i}.png", np.full((4, 6, 3), 100))
        frames.append({"file_path": f"images/frame_{i}.png", "transform_matrix": POSE[:3]})
    frames[1].update(fl_x=7.0, cx=2.5)
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"fl_x": 5.0, "fl_y": 6.0, "cx": 3.1, "cy": 1.9, "w": 6, "h": 4, "frames": frames}))
    data = load_dataset(tmp_path)
    assert [data.camera(i).fx for i in range(3)] == [5, 7, 5]
    assert data.camera(1).cx == 2.5 and data.camera(1).fy == 6
    assert load_dataset(tmp_path, downscale=2).camera(1).fx == 3.5
    frames[2]["w"] = 8
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"fl_x": 5.0, "fl_y": 6.0, "cx": 3.1, "cy": 1.9, "w": 6, "h": 4, "frames": frames}))
    with pytest.raises(InputError, match="different image sizes"):
        load_dataset(tmp_path)
    frames[2].update(w=6, fl_y=-1)
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"fl_x": 5.0, "fl_y": 6.0, "cx": 3.1, "cy": 1.9, "w": 6, "h": 4, "frames": frames}))
    with pytest.raises(InputError, match=r"frames\[2\].*fl_y"):
        load_dataset(tmp_path)


@pytest.mark.parametrize("layout", ["nerfstudio", "blender"])
@pytest.mark.parametrize("escape", ["absolute", "climbing"])
def test_frames_stay_inside_the_folder(tmp_path, capsys, layout, escape):
    """A transforms file from elsewhere cannot make training read a file outside its folder
    without --frames-outside; the refusal names the frame."""
    secret = tmp_path / "elsewhere" / "secret.png"
    write_png(secret, np.full((4, 6, 3), 7))
    root = tmp_path / "capture"
    path = str(secret) if escape == "absolute" else "../elsewhere/secret.png"
    if layout == "nerfstudio":
        write_png(root / "images" / "a.png", np.full((4, 6, 3), 100))
        frames = [{"file_path": "images/a.png", "transform_matrix": POSE},
                  {"file_path": path, "transform_matrix": POSE}]
        (root / "transforms.json").write_text(json.dumps(
            {"fl_x": 5.0, "fl_y": 5.0, "cx": 3, "cy": 2, "w": 6, "h": 4, "frames": frames}))
    else:
        blender_folder(root)
        data = json.loads((root / "transforms_test.json").read_text())
        data["frames"][0]["file_path"] = path[:-4]
        (root / "transforms_test.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match=r"frames\[\d\]: file_path .* lies outside"):
        load_dataset(root)
    expect_error(main, ["train", str(root)], "(use --frames-outside to read it)", capsys)
    data = load_dataset(root, frames_outside=True)
    assert data.frames_outside and np.allclose(data.images[-1 if layout == "nerfstudio" else 2],
                                               7 / 255)


def test_simulated_dataset_joins_its_weights(tmp_path):
    out = tmp_path / "cb"
    assert main(["simulate", "cornell-box", str(out), "--resolution", "8", "--spp", "2",
                 "--views", "3", "1", "2"]) == 0
    data = load_dataset(out, background=(0, 0, 0))
    stack = read_stack(out / "weights.npz")
    train = join_weights(data, stack, "train")
    test = join_weights(data, stack, "test")
    assert train.shape == (3, 8, 8, 15) and test.shape == (2, 8, 8, 15)
    assert np.array_equal(test[1], stack.weights[5])
    # on a black background the composited image is the premultiplied colour
    recomposed = np.clip(weights_to_rgb(train, stack.palette, "transport", 2), 0, 1)
    assert np.abs(recomposed - data.images[data.indices("train")]).max() < 1.5 / 255


def _stack(names, size=(4, 6), m=3):
    return WeightStack(palette=np.eye(3), weights=[np.full((*size, m), 1 / m)] * len(names),
                       names=names)


def test_stack_from_one_split_folder_matches_by_trailing_name(tmp_path):
    data = load_dataset(blender_folder(tmp_path))
    weights = join_weights(data, _stack(["r_0.png", "r_1.png"]), "train")
    assert weights.shape == (2, 4, 6, 3)


def test_join_errors_name_the_frames(tmp_path):
    data = load_dataset(blender_folder(tmp_path))
    with pytest.raises(InputError, match="train frames without weights in the stack: train/r_1"):
        join_weights(data, _stack(["train/r_0.png"]))
    with pytest.raises(InputError, match="not frames of .*: other.png"):
        join_weights(data, _stack(["train/r_0.png", "train/r_1.png", "other.png"]))
    with pytest.raises(InputError, match="are not 6x4"):
        join_weights(data, _stack(["train/r_0.png", "train/r_1.png"], size=(5, 5)))
    data.names[1] = "train/b/r_0.png"  # two train frames now end in r_0.png
    with pytest.raises(InputError, match="matches several train frames"):
        join_weights(data, _stack(["r_0.png"]))


@pytest.mark.parametrize("edit, message", [
    (lambda root: (root / "transforms_train.json").write_text("{"), "not valid JSON"),
    (lambda root: (root / "transforms_train.json").write_text(
        json.dumps({"camera_angle_x": -1, "frames": []})), "'camera_angle_x'"),
    (lambda root: (root / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": 0.6, "frames": [{"file_path": "train/r_0",
                                            "transform_matrix": [[1, 0]]}]})),
     "'transform_matrix' must be 4x4"),
    (lambda root: (root / "train" / "r_1.png").unlink(), "does not exist"),
    (lambda root: (root / "train" / "r_1.png").write_bytes(b"no png"), "cannot read image"),
    (lambda root: write_png(root / "train" / "r_1.png", np.zeros((5, 5, 4))), "images"),
])
def test_malformed_datasets(tmp_path, edit, message):
    root = blender_folder(tmp_path)
    edit(root)
    with pytest.raises(InputError, match=message):
        load_dataset(root)


def test_folder_without_transforms(tmp_path):
    with pytest.raises(InputError, match="holds none of transforms_train.json"):
        load_dataset(tmp_path)


def test_decompression_bomb_as_dataset_frame(tmp_path):
    (tmp_path / "train").mkdir()
    png_header_only(tmp_path / "train" / "r_0.png", 100000, 100000)
    frames = [{"file_path": "train/r_0", "transform_matrix": np.eye(4).tolist()}]
    (tmp_path / "transforms_train.json").write_text(
        json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    with pytest.raises(InputError, match="declares more than") as refused:
        load_dataset(tmp_path)
    assert refused.value.fixes == (("max_pixels", "to allow more"),)


def test_nan_camera_matrix(tmp_path):
    (tmp_path / "train").mkdir()
    Image.fromarray(np.zeros((2, 2, 3), np.uint8)).save(tmp_path / "train" / "r_0.png")
    pose = np.eye(4).tolist()
    pose[0][3] = float("nan")
    (tmp_path / "transforms_train.json").write_text(json.dumps(
        {"camera_angle_x": 0.7, "frames": [{"file_path": "train/r_0", "transform_matrix": pose}]}))
    with pytest.raises(InputError, match="NaN"):
        load_dataset(tmp_path)


def test_downscale_averages_blocks_and_scales_the_camera(still_life):
    full = load_dataset(still_life)
    half = load_dataset(still_life, downscale=2)
    assert half.images.shape[1:3] == (8, 8) and half.downscale == 2
    assert half.intrinsics.fx == full.intrinsics.fx / 2
    assert half.intrinsics.cx == full.intrinsics.cx / 2
    # composited colours average like the files' pixels, premultiplied by alpha
    blocks = full.images.reshape(len(full.images), 8, 2, 8, 2, 3).mean((2, 4))
    assert np.allclose(half.images, blocks, atol=1e-6)
    assert np.allclose(half.alpha, full.alpha.reshape(-1, 8, 2, 8, 2).mean((2, 4)), atol=1e-6)
    stack = read_stack(still_life / "weights.npz")  # of the files' size
    weights, full_weights = join_weights(half, stack), join_weights(full, stack)
    assert np.allclose(weights, full_weights.reshape(-1, 8, 2, 8, 2, 4).mean((2, 4)), atol=1e-6)


@pytest.mark.parametrize("factor", [0, 65, 2.5, True])
def test_bad_downscale_is_refused(still_life, factor):
    with pytest.raises(InputError, match="downscale"):
        load_dataset(still_life, downscale=factor)


def test_an_llff_capture_is_read_with_its_split_bounds_and_poses(tmp_path, rng):
    poses, bounds = llff_capture(tmp_path, rng)
    dataset = load_dataset(tmp_path)
    assert dataset.layout == "llff" and dataset.names[0] == "images_2/IMG_0000.png"
    assert [i for i, s in enumerate(dataset.splits) if s == "test"] == [0, 8]  # llffhold
    assert dataset.intrinsics.width == 8 and dataset.intrinsics.fx == pytest.approx(10.0)
    # plain numbers, as a checkpoint read as data needs them (numpy's were refused)
    assert {type(v) for v in vars(dataset.intrinsics).values()} == {int, float}
    factor = 1 / (bounds.min() * 0.75)
    np.testing.assert_allclose(dataset.bounds, bounds * factor)
    assert dataset.bounds.min() == pytest.approx(1 / 0.75)
    for i in range(1, len(poses)):  # the same cameras, up to the world's frame and scale
        truth = np.linalg.inv(poses[0]) @ poses[i]
        read = np.linalg.inv(dataset.poses[0]) @ dataset.poses[i]
        np.testing.assert_allclose(read[:3, :3], truth[:3, :3], atol=1e-9)
        np.testing.assert_allclose(read[:3, 3], truth[:3, 3] * factor, atol=1e-9)
    assert np.allclose(dataset.poses[:, :3, 3].mean(0), 0, atol=1e-9)  # centred
    assert dataset.poses[:, :3, 2].mean(0) @ [0, 0, 1] > 0.99  # looking down -z


@pytest.mark.parametrize("change, message", [
    (lambda t: t[:, :16], "(N, 17)"),
    (lambda t: np.where(np.arange(17) == 15, np.nan, t), "NaN"),
    (lambda t: np.where(np.arange(17) == 16, 0.5, t), "near < far"),
    (lambda t: t[:3], "3 rows for the 10 photos"),
])
def test_a_poses_bounds_file_that_lies_is_one_line(change, message, tmp_path, rng, capsys):
    llff_capture(tmp_path, rng)
    np.save(tmp_path / "poses_bounds.npy", change(np.load(tmp_path / "poses_bounds.npy")))
    assert main(["train", str(tmp_path), "-o", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err
