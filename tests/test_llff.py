"""LLFF dataparser: splits, intrinsics, camera axes and the recorded transform (virgi_ns.data.llff)."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from virgi_ns.data.llff import LLFFDataParserConfig
from virgi_ns.errors import InputError

from conftest import venv_command

FULL_H, FULL_W, FULL_F = 60.0, 80.0, 70.0  # the hwf row: poses "solved" on 80x60 images
SMALL_W, SMALL_H = 20, 15  # the images we write: 4x smaller


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q * np.linalg.det(q)  # det +1


def make_scene(root: Path, n: int = 10, seed: int = 0, images_dir: str = "images_4") -> dict:
    """A tiny LLFF capture from known OpenCV cameras (x right, y down, z forward), with PNGs."""
    rng = np.random.default_rng(seed)
    R_cv = np.stack([_random_rotation(rng) for _ in range(n)])  # camera-to-world rotations
    C = rng.normal(size=(n, 3)) * 2.0
    # LLFF's columns, written from their definition: [down, right, back] = [+y_cv, +x_cv, -z_cv]
    rows = np.zeros((n, 3, 5))
    rows[:, :, 0] = R_cv[:, :, 1]
    rows[:, :, 1] = R_cv[:, :, 0]
    rows[:, :, 2] = -R_cv[:, :, 2]
    rows[:, :, 3] = C
    rows[:, :, 4] = [FULL_H, FULL_W, FULL_F]
    bounds = np.tile([0.5, 10.0], (n, 1))
    root.mkdir(parents=True, exist_ok=True)
    np.save(root / "poses_bounds.npy", np.concatenate([rows.reshape(n, 15), bounds], 1))
    (root / images_dir).mkdir()
    for i in range(n):
        pixels = np.full((SMALL_H, SMALL_W, 3), i * 20, dtype=np.uint8)
        Image.fromarray(pixels).save(root / images_dir / f"img_{i:03d}.png")
    return {"R_cv": R_cv, "C": C}


def _parse(root: Path, split: str, **kw):
    return LLFFDataParserConfig(data=root, images_dir="images_4", **kw).setup().get_dataparser_outputs(split)


def test_splits_and_intrinsics(tmp_path: Path) -> None:
    make_scene(tmp_path, n=10)
    train, test = _parse(tmp_path, "train"), _parse(tmp_path, "test")
    assert [p.name for p in test.image_filenames] == ["img_000.png", "img_008.png"]
    assert [p.name for p in train.image_filenames] == [f"img_{i:03d}.png" for i in range(10) if i % 8]
    cams = train.cameras
    assert (cams.width == SMALL_W).all() and (cams.height == SMALL_H).all()
    assert torch.allclose(cams.fx, torch.tensor(FULL_F * SMALL_W / FULL_W))
    assert torch.allclose(cams.fy, torch.tensor(FULL_F * SMALL_W / FULL_W))
    assert torch.allclose(cams.cx, torch.tensor(SMALL_W / 2)) and torch.allclose(cams.cy, torch.tensor(SMALL_H / 2))
    assert "points3D_xyz" not in train.metadata  # no COLMAP model: random initialisation


def test_axes_match_opencv_cameras(tmp_path: Path) -> None:
    """Each output camera is the known OpenCV camera, moved by the recorded transform, in OpenGL axes."""
    truth = make_scene(tmp_path, n=10, seed=3)
    out = _parse(tmp_path, "train")
    idx = [i for i in range(10) if i % 8]
    T = out.dataparser_transform.double().numpy()  # 3x4, rigid
    s = out.dataparser_scale
    c2w = out.cameras.camera_to_worlds.double().numpy()
    assert np.allclose(T[:, :3] @ T[:, :3].T, np.eye(3), atol=1e-5)
    for k, i in enumerate(idx):
        R, C = truth["R_cv"][i], truth["C"][i]
        centre = s * (T[:, :3] @ C + T[:, 3])
        forward = T[:, :3] @ R[:, 2]  # viewing direction (OpenCV +z)
        up = T[:, :3] @ -R[:, 1]  # image up (OpenCV -y)
        right = T[:, :3] @ R[:, 0]
        assert np.allclose(c2w[k, :, 3], centre, atol=1e-4)
        assert np.allclose(-c2w[k, :, 2], forward, atol=1e-4)  # OpenGL looks down -z
        assert np.allclose(c2w[k, :, 1], up, atol=1e-4)
        assert np.allclose(c2w[k, :, 0], right, atol=1e-4)


def test_pixel_ray_hits_projected_point(tmp_path: Path) -> None:
    """A point projected with the OpenCV pinhole model lies on nerfstudio's ray through that pixel."""
    truth = make_scene(tmp_path, n=10, seed=5)
    out = _parse(tmp_path, "train")
    T = out.dataparser_transform.double().numpy()
    s = out.dataparser_scale
    f = FULL_F * SMALL_W / FULL_W
    rng = np.random.default_rng(1)
    for k, i in enumerate([i for i in range(10) if i % 8]):
        R, C = truth["R_cv"][i], truth["C"][i]
        p_cam = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(1.0, 4.0)])
        X = R @ p_cam + C
        u = f * p_cam[0] / p_cam[2] + SMALL_W / 2
        v = f * p_cam[1] / p_cam[2] + SMALL_H / 2
        rays = out.cameras.generate_rays(camera_indices=k, coords=torch.tensor([[v, u]], dtype=torch.float32))
        o = rays.origins.double().numpy().reshape(3)
        d = rays.directions.double().numpy().reshape(3)
        X_out = s * (T[:, :3] @ X + T[:, 3])
        to_point = (X_out - o) / np.linalg.norm(X_out - o)
        assert np.dot(to_point, d / np.linalg.norm(d)) > 1 - 1e-6


def test_saved_transform_maps_original_centres(tmp_path: Path) -> None:
    truth = make_scene(tmp_path / "scene", n=9, seed=7)
    out = _parse(tmp_path / "scene", "train")
    out.save_dataparser_transform(tmp_path / "dataparser_transforms.json")
    saved = json.loads((tmp_path / "dataparser_transforms.json").read_text())
    T, s = np.array(saved["transform"]), saved["scale"]
    centres = s * (truth["C"] @ T[:, :3].T + T[:, 3])
    idx = [i for i in range(9) if i % 8]
    assert np.allclose(out.cameras.camera_to_worlds[:, :, 3].numpy(), centres[idx], atol=1e-4)
    # auto scaling: the farthest camera coordinate (over all frames) is 1
    assert np.isclose(np.abs(centres).max(), 1.0, atol=1e-5)


@pytest.mark.parametrize(
    "damage, message",
    [
        ("drop_image", "images but poses_bounds.npy has"),
        ("no_poses", "poses_bounds.npy"),
        ("bad_shape", "N x 17"),
        ("nan", "NaN"),
        ("no_folder", "no such image folder"),
    ],
)
def test_bad_input_is_one_clear_error(tmp_path: Path, damage: str, message: str) -> None:
    make_scene(tmp_path, n=4)
    if damage == "drop_image":
        (tmp_path / "images_4" / "img_003.png").unlink()
    elif damage == "no_poses":
        (tmp_path / "poses_bounds.npy").unlink()
    elif damage == "bad_shape":
        np.save(tmp_path / "poses_bounds.npy", np.zeros((4, 15)))
    elif damage == "nan":
        arr = np.load(tmp_path / "poses_bounds.npy")
        arr[1, 3] = np.nan
        np.save(tmp_path / "poses_bounds.npy", arr)
    elif damage == "no_folder":
        shutil.rmtree(tmp_path / "images_4")
    with pytest.raises(InputError, match=message):
        _parse(tmp_path, "train")


def test_fern(shared_data) -> None:
    fern = shared_data.need("fern", "fern/poses_bounds.npy", "fern/images_8")
    hwf = np.load(fern / "poses_bounds.npy")[0, :15].reshape(3, 5)[:, 4]
    cfg = LLFFDataParserConfig(data=fern, images_dir="images_8")
    train = cfg.setup().get_dataparser_outputs("train")
    test = cfg.setup().get_dataparser_outputs("test")
    assert len(train.image_filenames) + len(test.image_filenames) == 20
    assert [p.name for p in test.image_filenames] == ["image000.png", "image008.png", "image016.png"]
    for cams in (train.cameras, test.cameras):
        assert (cams.width == 504).all() and (cams.height == 378).all()
        assert torch.allclose(cams.fx, torch.tensor(hwf[2] * 504 / 4032, dtype=torch.float32))
        assert torch.allclose(cams.fy, cams.fx)
    with Image.open(test.image_filenames[0]) as im:
        assert im.size == (504, 378)


def test_beercan_matches_its_colmap_model(shared_data) -> None:
    """LLFF poses keep COLMAP's world: our cameras equal COLMAP's (OpenCV) cameras, moved by the recorded
    transform, and the seeded points sit where COLMAP puts them relative to each camera."""
    from nerfstudio.data.utils.colmap_parsing_utils import qvec2rotmat, read_images_binary, read_points3D_binary

    scene = shared_data.need("beercan", "beercan/poses_bounds.npy", "beercan/images",
                             "beercan/sparse/0/images.bin", "beercan/sparse/0/points3D.bin")
    out = LLFFDataParserConfig(data=scene).setup().get_dataparser_outputs("train")
    images = sorted(read_images_binary(scene / "sparse/0/images.bin").values(), key=lambda im: im.name)
    names = [p.name for p in out.image_filenames]
    images = [im for im in images if im.name in names]
    assert [im.name for im in images] == names and len(names) == 71 - 9
    T = out.dataparser_transform.double().numpy()
    s = out.dataparser_scale
    flip = np.diag([1.0, -1.0, -1.0])  # OpenCV -> OpenGL camera axes
    pts = np.stack([p.xyz for p in read_points3D_binary(scene / "sparse/0/points3D.bin").values()])
    pts_out = out.metadata["points3D_xyz"].double().numpy()
    for k in (0, 30, len(images) - 1):
        w2c_R = qvec2rotmat(images[k].qvec)
        C = -w2c_R.T @ images[k].tvec
        c2w = out.cameras.camera_to_worlds[k].double().numpy()
        assert np.allclose(c2w[:, :3], T[:, :3] @ w2c_R.T @ flip, atol=1e-4)
        assert np.allclose(c2w[:, 3], s * (T[:, :3] @ C + T[:, 3]), atol=1e-4)
        in_cam_colmap = (pts - C) @ w2c_R.T
        in_cam_ours = (pts_out - c2w[:, 3]) @ c2w[:, :3] @ flip / s
        assert np.allclose(in_cam_ours, in_cam_colmap, atol=1e-3 * np.abs(in_cam_colmap).max())


def test_ns_train_help_lists_llff(shared_data, tmp_path: Path) -> None:
    fern = shutil.copytree(shared_data.need("fern", "fern/poses_bounds.npy"), tmp_path / "fern")
    out = subprocess.run(
        [*venv_command("ns-train", "nerfstudio.scripts.train"), "splatfacto", "llff", "--data", str(fern), "--help"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "--images-dir" in out.stdout and "--llffhold" in out.stdout
