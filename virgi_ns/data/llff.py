"""LLFF dataparser: ``ns-train <method> llff --data DIR [--images-dir images_8]``.

An LLFF capture is ``DIR/poses_bounds.npy`` (one row of 17 numbers per image, in sorted file-name order)
beside an image folder. Each row is a 3x5 matrix, row-major, then the near and far depth bounds. Its
first three columns are the camera-to-world rotation with camera axes [down, right, back], the fourth
is the camera centre, and the fifth is [height, width, focal] of the images the poses were solved on
(often the full-resolution photos, while training uses a downscaled folder such as ``images_8``).

The parser turns the axes into nerfstudio's OpenGL camera convention [right, up, back], scales the
focal length to the width of the images actually used, holds out every ``llffhold``-th frame
(0, 8, 16, ...) for evaluation, and orients, centres and scales the poses as nerfstudio's own
parsers do, recording that transform so ``dataparser_transforms.json`` is written as usual. Where
the capture also holds the COLMAP model LLFF was computed from (``sparse/0/points3D.bin``; LLFF keeps
COLMAP's world frame), its points seed the scene; otherwise no points are given and splatfacto-style
models start from random points.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple, Type

import numpy as np
import torch
from jaxtyping import Float
from PIL import Image
from torch import Tensor

from nerfstudio.cameras import camera_utils
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.plugins.registry_dataparser import DataParserSpecification
from nerfstudio.utils.rich_utils import CONSOLE

from virgi_ns.errors import InputError
# the checkpoint-loading work-arounds, in place once entry-point discovery imports this dataparser
from virgi_ns.nerfstudio import compat  # noqa: F401

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass
class LLFFDataParserConfig(DataParserConfig):
    """LLFF scenes: ``poses_bounds.npy`` beside an image folder."""

    _target: Type = field(default_factory=lambda: LLFF)
    data: Path = Path()
    """Directory holding poses_bounds.npy and the image folder."""
    images_dir: str = "images"
    """Image folder inside the data directory (e.g. images_8 for LLFF's 8x downscaled images)."""
    llffhold: int = 8
    """Every llffhold-th frame, starting at frame 0, is held out for evaluation (LLFF convention). 0: none."""
    orientation_method: Literal["pca", "up", "vertical", "none"] = "up"
    """How the poses are rotated (nerfstudio's camera_utils.auto_orient_and_center_poses)."""
    center_method: Literal["poses", "focus", "none"] = "poses"
    """How the poses are centred."""
    auto_scale_poses: bool = True
    """Scale the poses to fit in [-1, 1]."""
    scale_factor: float = 1.0
    """Further scale applied to the poses (after auto scaling)."""
    scene_scale: float = 1.0
    """Half-size of the scene box, in the scaled coordinates."""
    load_3D_points: bool = True
    """Seed with COLMAP's sparse points when the capture has sparse/0/points3D.bin."""


def llff_to_opengl(poses_3x5: Float[np.ndarray, "n 3 5"]) -> Float[np.ndarray, "n 3 4"]:
    """Camera-to-world [R | t] with camera axes [right, up, back] from LLFF's [down, right, back] columns."""
    down, right, back, centre = (poses_3x5[:, :, i] for i in range(4))
    return np.stack([right, -down, back, centre], axis=-1)


def read_poses_bounds(path: Path) -> Tuple[Float[np.ndarray, "n 3 5"], Float[np.ndarray, "n 2"]]:
    """The 3x5 pose+hwf matrices and the near/far bounds of ``poses_bounds.npy``."""
    if not path.is_file():
        raise InputError(f"{path}: no such file (an LLFF scene needs poses_bounds.npy)")
    try:
        arr = np.load(path)
    except Exception as err:  # numpy raises several types for unreadable files
        raise InputError(f"{path}: not a readable .npy file ({err})") from None
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] == 0:
        raise InputError(f"{path}: expected an N x 17 array, got shape {tuple(arr.shape)}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise InputError(f"{path}: {int((~np.isfinite(arr)).any(axis=1).sum())} rows hold NaN or Inf")
    return arr[:, :15].reshape(-1, 3, 5), arr[:, 15:17]


def list_images(folder: Path) -> List[Path]:
    """Image files of ``folder`` in sorted name order (the order of LLFF's pose rows)."""
    if not folder.is_dir():
        raise InputError(f"{folder}: no such image folder (choose one with --images-dir)")
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))


def eval_indices(num_frames: int, llffhold: int) -> List[int]:
    """LLFF hold-out: frames 0, llffhold, 2*llffhold, ... (none when llffhold <= 0)."""
    return list(range(0, num_frames, llffhold)) if llffhold > 0 else []


class LLFF(DataParser):
    """Reads an LLFF capture into nerfstudio cameras."""

    config: LLFFDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs: Optional[Dict]) -> DataparserOutputs:
        data = Path(self.config.data)
        poses_3x5, _bounds = read_poses_bounds(data / "poses_bounds.npy")
        image_filenames = list_images(data / self.config.images_dir)
        n = len(poses_3x5)
        if len(image_filenames) != n:
            raise InputError(
                f"{data / self.config.images_dir}: {len(image_filenames)} images but poses_bounds.npy has {n} rows"
            )

        # intrinsics: the hwf row is for the images the poses were solved on; rescale to the images used
        with Image.open(image_filenames[0]) as im:
            width, height = im.size
        hwf = poses_3x5[0, :, 4]
        if not (hwf > 0).all():
            raise InputError(f"{data / 'poses_bounds.npy'}: height, width and focal must be positive, got {hwf}")
        scale = width / hwf[1]
        if abs(height / hwf[0] - scale) > 0.01 * scale:
            CONSOLE.print(
                f"[bold yellow]Warning: {image_filenames[0].name} is {width}x{height}, but poses_bounds.npy's "
                f"images were {int(hwf[1])}x{int(hwf[0])}; the aspect ratios differ, focal scaled by width"
            )
        focal = float(hwf[2] * scale)

        held_out = eval_indices(n, self.config.llffhold)
        if split == "train":
            indices = [i for i in range(n) if i not in set(held_out)]
        elif split in ("val", "test"):
            indices = held_out
        else:
            raise ValueError(f"Unknown dataparser split {split}")

        c2w = np.tile(np.eye(4), (n, 1, 1))
        c2w[:, :3, :] = llff_to_opengl(poses_3x5)
        poses = torch.from_numpy(c2w.astype(np.float32))
        poses, transform_matrix = camera_utils.auto_orient_and_center_poses(
            poses, method=self.config.orientation_method, center_method=self.config.center_method
        )
        scale_factor = 1.0
        if self.config.auto_scale_poses:
            scale_factor /= float(torch.max(torch.abs(poses[:, :3, 3])))
        scale_factor *= self.config.scale_factor
        poses[:, :3, 3] *= scale_factor

        idx = torch.tensor(indices, dtype=torch.long)
        cameras = Cameras(
            camera_to_worlds=poses[idx, :3, :4],
            fx=focal,
            fy=focal,
            cx=width / 2.0,
            cy=height / 2.0,
            width=width,
            height=height,
            camera_type=CameraType.PERSPECTIVE,
        )
        s = self.config.scene_scale
        scene_box = SceneBox(aabb=torch.tensor([[-s, -s, -s], [s, s, s]], dtype=torch.float32))

        metadata: Dict = {}
        points_file = data / "sparse" / "0" / "points3D.bin"
        if self.config.load_3D_points and points_file.is_file():
            metadata.update(load_sparse_points(points_file, transform_matrix, scale_factor))

        return DataparserOutputs(
            image_filenames=[image_filenames[i] for i in indices],
            cameras=cameras,
            scene_box=scene_box,
            dataparser_transform=transform_matrix,
            dataparser_scale=scale_factor,
            metadata=metadata,
        )


def load_sparse_points(
    path: Path, transform_matrix: Float[Tensor, "3 4"], scale_factor: float
) -> Dict[str, Tensor]:
    """COLMAP points (LLFF's world frame) moved into the parser's output frame, as nerfstudio's metadata."""
    from nerfstudio.data.utils.colmap_parsing_utils import read_points3D_binary

    points = read_points3D_binary(path)
    if not points:
        return {}
    xyz = torch.from_numpy(np.stack([p.xyz for p in points.values()]).astype(np.float32))
    rgb = torch.from_numpy(np.stack([p.rgb for p in points.values()]).astype(np.uint8))
    xyz = (xyz @ transform_matrix[:, :3].T + transform_matrix[:, 3]) * scale_factor
    return {"points3D_xyz": xyz, "points3D_rgb": rgb}


llff_dataparser = DataParserSpecification(
    config=LLFFDataParserConfig(),
    description="LLFF scenes (poses_bounds.npy + images/); every 8th frame held out for evaluation",
)
