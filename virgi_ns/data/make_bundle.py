"""Make a bundle (a small nerfstudio-format capture) from the COLMAP beercan, or shrink one.

``scripts/make_bundle.py`` is the command line::

    python scripts/make_bundle.py                       # the bundled scene (32 views, 1/2 size)
    python scripts/make_bundle.py --downscale 1 --out /tmp/beercan_full   # same views, full size

Reads ``../shared/data/beercan`` (COLMAP ``sparse/0``, SIMPLE_RADIAL cameras, one per image) and
writes a nerfstudio-format capture:

- ``images/NNNN.jpg``: every ``--views``-th-spread image (evenly spaced over the sorted names),
  **undistorted** (the radial k1 removed; the focal length grows just enough that every output
  pixel has a source pixel, the principal point stays), then downscaled by ``--downscale`` with
  area averaging;
- ``transforms.json``: per-frame pinhole intrinsics and camera-to-world matrices (OpenGL camera
  axes) in COLMAP's world frame, ``applied_transform`` the identity, so the capture frame of
  this folder *is* COLMAP's frame (an INRIA ``.ply`` trained on the COLMAP model drops in);
- ``sparse_pc.ply``: COLMAP's sparse points (x, y, z float; red, green, blue uchar).

Deterministic: the same source gives byte-identical files (fixed JPEG quality, no timestamps).
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rich.progress import track

from virgi_ns.errors import InputError, atomic_path

REPO = Path(__file__).resolve().parents[2]
DEFAULT_SOURCE = REPO.parent / "shared" / "data" / "beercan"
DEFAULT_OUT = REPO / "virgi_ns" / "assets" / "beercan_small"


@dataclass
class Args:
    source: Path = DEFAULT_SOURCE
    """COLMAP capture: images/ and sparse/0/{cameras,images,points3D}.bin."""
    out: Path = DEFAULT_OUT
    """Output folder (created; its images/, transforms.json and sparse_pc.ply are replaced)."""
    views: int = 32
    """Number of views kept, evenly spread over the sorted image names."""
    downscale: int = 2
    """Integer downscale factor of the undistorted images."""
    jpeg_quality: int = 90


def pick_views(n_total: int, n: int) -> list[int]:
    """``n`` indices spread evenly over ``range(n_total)`` (first and last included)."""
    if not 1 <= n <= n_total:
        raise InputError(f"--views must be in 1..{n_total}, got {n}")
    return sorted({int(round(i)) for i in np.linspace(0, n_total - 1, n)})


def camera_params(cam) -> tuple[float, float, float, float, float]:
    """(fx, fy, cx, cy, k1) of a COLMAP camera (pinhole models have k1 = 0)."""
    p = cam.params
    if cam.model == "SIMPLE_RADIAL":
        return p[0], p[0], p[1], p[2], p[3]
    if cam.model == "SIMPLE_PINHOLE":
        return p[0], p[0], p[1], p[2], 0.0
    if cam.model == "PINHOLE":
        return p[0], p[1], p[2], p[3], 0.0
    raise InputError(f"camera {cam.id}: model {cam.model} is not handled (SIMPLE_RADIAL, SIMPLE_PINHOLE, PINHOLE)")


def _distorted_source(u: np.ndarray, v: np.ndarray, f_new: float, fx: float, fy: float, cx: float, cy: float,
                      k1: float) -> tuple[np.ndarray, np.ndarray]:
    """Source pixel coordinates (continuous, pixel centres at +0.5) of output coordinates ``u, v``
    of a pinhole camera with focal ``f_new`` (same principal point)."""
    x = (u - cx) / f_new
    y = (v - cy) / (f_new * fy / fx)
    r2 = x * x + y * y
    d = 1.0 + k1 * r2
    return fx * x * d + cx, fy * y * d + cy


def undistorted_focal(W: int, H: int, fx: float, fy: float, cx: float, cy: float, k1: float) -> float:
    """Smallest focal ``>= fx`` for which every output pixel centre samples inside the source."""
    if k1 == 0.0:
        return fx
    edge = np.arange(W) + 0.5
    side = np.arange(H) + 0.5
    u = np.concatenate([edge, edge, np.full(H, 0.5), np.full(H, W - 0.5)])
    v = np.concatenate([np.full(W, 0.5), np.full(W, H - 0.5), side, side])

    def inside(f: float) -> bool:
        su, sv = _distorted_source(u, v, f, fx, fy, cx, cy, k1)
        return bool(((su >= 0.5) & (su <= W - 0.5) & (sv >= 0.5) & (sv <= H - 0.5)).all())

    if inside(fx):
        return fx
    lo, hi = fx, fx * 2.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if inside(mid) else (mid, hi)
    return hi


def undistort(img: np.ndarray, fx: float, fy: float, cx: float, cy: float, k1: float) -> tuple[np.ndarray, float]:
    """Undistorted image (same size and principal point) and its focal length (x; y keeps fy/fx)."""
    import cv2

    H, W = img.shape[:2]
    f_new = undistorted_focal(W, H, fx, fy, cx, cy, k1)
    if f_new == fx and k1 == 0.0:
        return img, fx
    uu, vv = np.meshgrid(np.arange(W, dtype=np.float64) + 0.5, np.arange(H, dtype=np.float64) + 0.5)
    su, sv = _distorted_source(uu, vv, f_new, fx, fy, cx, cy, k1)
    # OpenCV indexes pixel centres at integers
    out = cv2.remap(img, (su - 0.5).astype(np.float32), (sv - 0.5).astype(np.float32), cv2.INTER_CUBIC,
                    borderMode=cv2.BORDER_REPLICATE)
    return out, f_new


def write_points_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Binary PLY of points with uchar colours (what nerfstudio's loaders read)."""
    from virgi_ns.io.plyfmt import ply_bytes

    rec = np.zeros(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                                    ("blue", "u1")])
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec["red"], rec["green"], rec["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    with atomic_path(path) as tmp:
        tmp.write_bytes(ply_bytes([("vertex", rec)]))


def qvec_to_rotmat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def make_bundle(args: Args) -> dict:
    """Write the capture; returns the transforms.json content."""
    import cv2
    from nerfstudio.data.utils.colmap_parsing_utils import (read_cameras_binary, read_images_binary,
                                                             read_points3D_binary)

    sparse = args.source / "sparse" / "0"
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        if not (sparse / name).is_file():
            raise InputError(f"not a COLMAP capture: {sparse / name} is missing")
    if args.downscale < 1:
        raise InputError(f"--downscale must be >= 1, got {args.downscale}")
    cams = read_cameras_binary(sparse / "cameras.bin")
    ims = sorted(read_images_binary(sparse / "images.bin").values(), key=lambda im: im.name)
    keep = pick_views(len(ims), args.views)
    (args.out / "images").mkdir(parents=True, exist_ok=True)
    for old in (args.out / "images").glob("*.jpg"):
        old.unlink()
    frames = []
    s = args.downscale
    for i in track(keep, description=f"undistorting {len(keep)} views"):
        im = ims[i]
        fx, fy, cx, cy, k1 = camera_params(cams[im.camera_id])
        src = args.source / "images" / im.name
        img = cv2.imread(str(src), cv2.IMREAD_COLOR)
        if img is None:
            raise InputError(f"cannot read {src}")
        und, f_new = undistort(img, fx, fy, cx, cy, k1)
        H, W = und.shape[:2]
        Wo, Ho = W // s, H // s
        if s > 1:
            und = cv2.resize(und[: Ho * s, : Wo * s], (Wo, Ho), interpolation=cv2.INTER_AREA)
        name = f"images/{Path(im.name).stem}.jpg"
        ok, buf = cv2.imencode(".jpg", und, [cv2.IMWRITE_JPEG_QUALITY, args.jpeg_quality])
        if not ok:
            raise InputError(f"cannot encode {name}")
        with atomic_path(args.out / name) as tmp:
            tmp.write_bytes(buf.tobytes())
        R = qvec_to_rotmat(np.asarray(im.qvec))
        t = np.asarray(im.tvec)
        c2w = np.eye(4)
        c2w[:3, :3] = R.T
        c2w[:3, 3] = -R.T @ t
        c2w[:3, 1:3] *= -1  # OpenCV camera axes -> OpenGL (nerfstudio)
        frames.append({
            "file_path": name,
            "fl_x": round(f_new / s, 6), "fl_y": round(f_new * fy / fx / s, 6),
            "cx": round(cx / s, 6), "cy": round(cy / s, 6), "w": Wo, "h": Ho,
            "transform_matrix": np.round(c2w, 9).tolist(),
            "colmap_image": im.name, "colmap_k1": round(float(k1), 9),
        })
    pts = read_points3D_binary(sparse / "points3D.bin")
    ids = sorted(pts)
    xyz = np.stack([pts[k].xyz for k in ids]).astype(np.float32)
    rgb = np.stack([pts[k].rgb for k in ids]).astype(np.uint8)
    write_points_ply(args.out / "sparse_pc.ply", xyz, rgb)
    meta = {
        "camera_model": "PINHOLE",
        "applied_transform": np.eye(4)[:3].tolist(),
        "ply_file_path": "sparse_pc.ply",
        "source": "beercan (COLMAP, SIMPLE_RADIAL), undistorted; made by scripts/make_bundle.py",
        "downscale": s,
        "frames": frames,
    }
    with atomic_path(args.out / "transforms.json") as tmp:
        tmp.write_text(json.dumps(meta, indent=1) + "\n")
    return meta


def shrink_bundle(src: Path, dst: Path, views: int, factor: int) -> Path:
    """A smaller copy of bundle ``src`` in ``dst``: its first ``views`` frames, images downscaled
    by ``factor`` (area averaging; intrinsics scaled to match). For tests and quick runs."""
    import cv2

    meta = json.loads((src / "transforms.json").read_text())
    frames = meta["frames"][:views]
    (dst / "images").mkdir(parents=True, exist_ok=True)
    for fr in frames:
        img = cv2.imread(str(src / fr["file_path"]), cv2.IMREAD_COLOR)
        if img is None:
            raise InputError(f"cannot read {src / fr['file_path']}")
        w, h = fr["w"] // factor, fr["h"] // factor
        img = cv2.resize(img[: h * factor, : w * factor], (w, h), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(dst / fr["file_path"]), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        for k in ("fl_x", "fl_y", "cx", "cy"):
            fr[k] = fr[k] / factor
        fr["w"], fr["h"] = w, h
    meta["frames"] = frames
    (dst / "transforms.json").write_text(json.dumps(meta))
    if "ply_file_path" in meta and (src / meta["ply_file_path"]).is_file():
        shutil.copyfile(src / meta["ply_file_path"], dst / meta["ply_file_path"])
    return dst


def main(args: Args) -> None:
    meta = make_bundle(args)
    f0 = meta["frames"][0]
    print(f"wrote {args.out}: {len(meta['frames'])} views at {f0['w']}x{f0['h']}, "
          f"{sum(p.stat().st_size for p in args.out.rglob('*') if p.is_file()) / 1e6:.2f} MB")
