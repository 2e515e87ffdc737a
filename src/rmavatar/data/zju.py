"""ZJU-MoCap used monocularly: one camera's video of a CoreView_3xx (or my_3xx) capture.

Layout: annots.npy (a pickled dict: cams {K, D, R, T} lists over the cameras, world-to-camera, T in
millimetres; ims: per frame {ims: relative image paths, one per camera}), Camera_B*/ images,
mask/ and mask_cihp/ PNGs at the same relative paths (any non-zero value is the person),
params/{i}.npy or new_params/{i}.npy (dicts: poses [1,72], Rh [1,3], Th [1,3], shapes [1,10]) with
vertices_world = SMPL(poses, shapes) R(Rh)^T + Th: the extra rotation Rh turns the posed body about the
world origin, not about the pelvis as SMPL's global_orient does. `zju_to_smpl_params` converts.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.ndimage import map_coordinates
from scipy.spatial.transform import Rotation

from rmavatar.data.dataset import Dataset, FrameRecord, warn
from rmavatar.data.io import load_object_npy, read_binary_mask
from rmavatar.render.camera import Camera
from rmavatar.utils import UserError

# subject -> (last train frame, last test frame), 1-based as the paper's table gives them (frames
# 1..456 are annots["ims"][0..455]). Train frames are taken 1 in 4, test frames all.
SPLITS = {
    "377": (456, 617), "386": (456, 646), "387": (456, 654),
    "392": (456, 556), "393": (456, 658), "394": (656, 859),
}
TRAIN_STEP = 4
MASK_MODES = ("union", "mask", "cihp")


def zju_to_smpl_params(Rh: np.ndarray, Th: np.ndarray, poses: np.ndarray, J0: np.ndarray) -> dict[str, np.ndarray]:
    """ZJU's (Rh, Th, poses) -> SMPL-format global_orient, body_pose, transl placing the same vertices.

    ZJU: x_world = R(Rh) SMPL(poses, shapes) + Th, where SMPL(...) already applies poses[:3] about the
    rest pelvis J0: SMPL(...) = R0 (X - J0) + J0 (X: the body articulated below the root).
    So x_world = R(Rh) R0 (X - J0) + R(Rh) J0 + Th, which is SMPL with
    global_orient = log(R(Rh) R0) and transl = Th + R(Rh) J0 - J0.

    Rh [N,3], Th [N,3] (metres), poses [N,72], J0 [N,3] or [3]: the rest pelvis of the body for these
    shapes (J0 does not depend on pose). Returns float32 global_orient [N,3], body_pose [N,69], transl [N,3].
    """
    Rh = np.asarray(Rh, np.float64).reshape(-1, 3)
    Th = np.asarray(Th, np.float64).reshape(-1, 3)
    poses = np.asarray(poses, np.float64).reshape(-1, 72)
    J0 = np.array(np.broadcast_to(np.asarray(J0, np.float64), Th.shape))
    R_h = Rotation.from_rotvec(Rh)
    R_g = R_h * Rotation.from_rotvec(poses[:, :3])
    transl = Th + R_h.apply(J0) - J0
    return {"global_orient": R_g.as_rotvec().astype(np.float32),
            "body_pose": poses[:, 3:].astype(np.float32),
            "transl": transl.astype(np.float32)}


def rest_pelvis_provider(body, gender: str | None = "neutral") -> Callable[[np.ndarray], np.ndarray]:
    """A function betas [N,10] -> rest pelvis J0 [N,3] from a body.

    body: a callable already of that form; a BodyModel (rmavatar.body); or a body spec string
    ("anny", "smpl:PATH") loaded with rmavatar.body.load_body_model. For an SMPL body the betas are
    used; other bodies (Anny) have their own shape space and take their default shape.
    """
    if isinstance(body, str):
        try:
            from rmavatar.body import load_body_model
        except ImportError as exc:
            raise UserError(f"cannot load body '{body}' for the ZJU conversion: {exc}") from None
        body = load_body_model(body, gender=gender)
    if not hasattr(body, "v_template"):
        if not callable(body):
            raise UserError(f"body must be a spec string, a BodyModel or a callable, got {type(body)}")
        return body

    def j0(betas: np.ndarray) -> np.ndarray:
        import torch

        n = len(betas)
        uses_betas = str(getattr(body, "spec", "")).startswith("smpl") and getattr(body, "num_betas", 0) > 0
        b = None
        if uses_betas:
            nb = body.num_betas
            full = np.zeros((n, nb), np.float32)
            full[:, :min(nb, betas.shape[1])] = betas[:, :nb]
            b = torch.as_tensor(full)
        zeros = torch.zeros
        with torch.no_grad():
            out = body(b, zeros(n, 3), zeros(n, 69), zeros(n, 3))
        return out.joints[:, 0].detach().cpu().numpy().astype(np.float64)

    return j0


def undistort_maps(K: np.ndarray, D: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel of the undistorted image (same K), where to sample the distorted one.

    OpenCV's model (k1, k2, p1, p2, k3) applied to the normalised coordinates of each output pixel, in
    the calibration's own pixel convention. Returns rows [H,W], cols [H,W] float32.
    """
    d = np.zeros(5)
    flat = np.asarray(D, np.float64).reshape(-1)[:5]
    d[:len(flat)] = flat
    k1, k2, p1, p2, k3 = d
    Kinv = np.linalg.inv(np.asarray(K, np.float64))
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pts = np.stack([u, v, np.ones_like(u)], -1) @ Kinv.T
    x, y = pts[..., 0] / pts[..., 2], pts[..., 1] / pts[..., 2]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 ** 3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    proj = np.stack([xd, yd, np.ones_like(xd)], -1) @ np.asarray(K, np.float64).T
    return proj[..., 1].astype(np.float32), proj[..., 0].astype(np.float32)


def remap(arr: np.ndarray, rows: np.ndarray, cols: np.ndarray, fill: str) -> np.ndarray:
    """Bilinear sampling of [H,W] or [H,W,C] at (rows, cols); fill "nearest" (images) or "zero" (masks)."""
    mode, cval = ("nearest", 0.0) if fill == "nearest" else ("constant", 0.0)
    if arr.ndim == 2:
        return map_coordinates(arr, [rows, cols], order=1, mode=mode, cval=cval).astype(np.float32)
    return np.stack([map_coordinates(arr[..., c], [rows, cols], order=1, mode=mode, cval=cval)
                     for c in range(arr.shape[2])], -1).astype(np.float32)


class ZJUDataset(Dataset):
    """ZJU-MoCap frames; undistorts images and masks of cameras that have distortion.

    distortion: {id(Camera) of the records: (K [3,3], D [5])} for the cameras in use.
    """

    def __init__(self, *, distortion: dict[int, tuple[np.ndarray, np.ndarray]], **kwargs):
        super().__init__(mask_reader=read_binary_mask, **kwargs)
        self._distortion = distortion
        self._maps: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def _read_pixels(self, rec: FrameRecord):
        image, mask = super()._read_pixels(rec)
        K, D = self._distortion[id(rec.camera)]
        if not np.any(D):
            return image, mask
        key = id(rec.camera)
        if key not in self._maps:
            self._maps[key] = undistort_maps(K, D, *self.source_size)
        rows, cols = self._maps[key]
        return np.clip(remap(image, rows, cols, "nearest"), 0, 1), np.clip(remap(mask, rows, cols, "zero"), 0, 1)


def _subject_id(name: str) -> str | None:
    found = re.findall(r"(\d{3})", name)
    return found[-1] if found else None


def _load_annots(path: Path) -> dict:
    annots = load_object_npy(path)  # numpy classes only: a hostile file cannot run code
    if not isinstance(annots, dict) or "cams" not in annots or "ims" not in annots:
        raise UserError(f"{path} must hold a dict with 'cams' and 'ims'")
    missing = [k for k in ("K", "D", "R", "T") if k not in annots["cams"]]
    if missing:
        raise UserError(f"{path}: cams is missing {missing}")
    return annots


def _load_params(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise UserError(f"SMPL parameters {path} do not exist")
    d = load_object_npy(path)  # numpy classes only: a hostile file cannot run code
    want = {"poses": 72, "Rh": 3, "Th": 3, "shapes": 10}
    out = {}
    for key, width in want.items():
        if not isinstance(d, dict) or key not in d:
            raise UserError(f"{path} is missing '{key}' (needs poses, Rh, Th, shapes)")
        arr = np.asarray(d[key], np.float64).reshape(-1)
        if arr.size < width:
            raise UserError(f"{path}: '{key}' has {arr.size} values, needs {width}")
        out[key] = arr[:width]
    return out


def _camera_index(value, num_cams: int, annots_path: Path, what: str) -> int:
    try:
        c = int(value)
    except (TypeError, ValueError):
        raise UserError(f"{what} must be an integer camera index, got {value!r}") from None
    if not 0 <= c < num_cams:
        raise UserError(f"{annots_path} has {num_cams} cameras (0..{num_cams - 1}); {what} {c} asked")
    return c


def open_zju(root: Path, size=None, cache_mb: float = 1024.0, camera=0, mask: str = "union",
             params: str | None = None, body="anny", views=None, **options) -> Dataset:
    """Read one ZJU-MoCap subject seen by one camera.

    camera: 0-based index into annots' camera lists (0 = Camera_B1). mask: "union" (mask/ or
    mask_cihp/, whichever exist, united: Neural Body's choice), "mask" or "cihp" (only that folder).
    params: "new_params" or "params" (default: new_params/ where it exists). body: what supplies the
    rest pelvis J0 for the Rh/Th conversion (see `rest_pelvis_provider`): use the body you train with.
    views: other cameras ("3,9,15", a list, or "all") whose images of the test frames (the train frames
    where there is no test split) form a ``novel_view`` split for novel-view evaluation.
    Splits: the paper's train/test frames for 377, 386, 387, 392, 393, 394 (train 1 in 4); another
    subject gets every 4th frame as train and no test.
    """
    if options:
        raise UserError(f"unknown ZJU options {sorted(options)} (known: camera, mask, params, body, views)")
    root = Path(root)
    annots_path = root / "annots.npy"
    annots = _load_annots(annots_path)
    cams = annots["cams"]
    num_cams = len(cams["K"])
    camera = _camera_index(camera, num_cams, annots_path, "camera")
    views = _view_indices(views, camera, num_cams, annots_path)
    if mask not in MASK_MODES:
        raise UserError(f"mask must be one of {MASK_MODES}, got {mask!r}")

    ims = annots["ims"]
    name = root.name
    plan = _frame_plan(name, len(ims), annots_path, camera, views)
    params_dir, offset = _params_folder(root, params)
    paths = _frame_paths(root, ims, plan, _mask_folders(root, mask), annots_path)

    used = sorted({i for pairs in plan.values() for i, _ in pairs})
    shapes, conv = _converted_params(params_dir, offset, used, body)
    row = {i: k for k, i in enumerate(used)}

    width, height = _image_size(paths[used[0], camera][0] if (used[0], camera) in paths else
                                next(iter(paths.values()))[0])
    cameras, distortion = _cameras(cams, plan, width, height)
    records = {
        split: [FrameRecord(index=i, image=paths[i, c][0], masks=paths[i, c][1], camera=cameras[c],
                            betas=shapes[row[i]].astype(np.float32),
                            global_orient=conv["global_orient"][row[i]],
                            body_pose=conv["body_pose"][row[i]], transl=conv["transl"][row[i]])
                for i, c in pairs]
        for split, pairs in plan.items()}
    return ZJUDataset(kind="zju", name=name if camera == 0 else f"{name}-cam{camera}", root=root,
                      records=records, source_size=(width, height), gender="neutral", fps=None, size=size,
                      cache_mb=cache_mb, distortion=distortion)


def _view_indices(views, camera: int, num_cams: int, annots_path: Path) -> list[int]:
    """The ``views`` option ("3,9,15", a list, "all", None or "") as checked camera indices; returns them
    ("all": every camera but ``camera``)."""
    if views is None or views == "":
        return []
    if views == "all":
        return [c for c in range(num_cams) if c != camera]
    items = views.split(",") if isinstance(views, str) else list(views)
    return [_camera_index(v, num_cams, annots_path, "view") for v in items]


def _frame_plan(name: str, num: int, annots_path: Path, camera: int, views: list[int]) -> dict[str, list]:
    """Which (frame, camera) pairs each split holds; returns {split: [(frame, camera)]}.

    The paper's train/test frames for the subjects in SPLITS, else every TRAIN_STEP-th frame as train and
    no test; with ``views``, a ``novel_view`` split of the test frames (train where there is no test)
    seen by those cameras."""
    sid = _subject_id(name)
    if sid in SPLITS:
        last_train, last_test = SPLITS[sid]
        if last_test > num:
            raise UserError(f"{annots_path} lists {num} frames; the paper's split for {sid} needs {last_test}")
        splits = {"train": list(range(0, last_train, TRAIN_STEP)), "test": list(range(last_train, last_test))}
    else:
        warn(f"{name}: no standard split; every {TRAIN_STEP}th frame is 'train', there is no test split")
        splits = {"train": list(range(0, num, TRAIN_STEP))}
    plan = {s: [(i, camera) for i in idx] for s, idx in splits.items()}
    if views:
        base = splits.get("test", splits["train"])
        plan["novel_view"] = [(i, c) for c in views for i in base]
    return plan


def _params_folder(root: Path, params: str | None) -> tuple[Path, int]:
    """The SMPL parameter folder (``params``, default new_params/ where it exists, else params/); returns
    (folder, number of its first file)."""
    if params is None:
        params = "new_params" if (root / "new_params").is_dir() else "params"
    params_dir = root / params
    if not params_dir.is_dir():
        raise UserError(f"folder {params_dir} does not exist (ZJU SMPL parameters: params/ or new_params/)")
    # CoreView_313/315 number their parameter files from 1, the others from 0.
    offset = 0 if (params_dir / "0.npy").is_file() or not (params_dir / "1.npy").is_file() else 1
    return params_dir, offset


def _mask_folders(root: Path, mask: str) -> tuple[Path, ...]:
    """The existing mask folders the ``mask`` mode reads; returns them (UserError if there is none)."""
    wanted = {"union": ("mask", "mask_cihp"), "mask": ("mask",), "cihp": ("mask_cihp",)}[mask]
    mask_dirs = tuple(root / m for m in wanted if (root / m).is_dir())
    if not mask_dirs:
        raise UserError(f"{root} has no mask folder ({' or '.join(str(root / m) for m in wanted)})")
    return mask_dirs


def _frame_paths(root: Path, ims, plan: dict[str, list], mask_dirs: tuple[Path, ...],
                 annots_path: Path) -> dict[tuple[int, int], tuple[Path, tuple[Path, ...]]]:
    """Image and existing mask files of every planned (frame, camera); returns {(frame, camera): (image,
    masks)}, checked to exist."""
    paths = {}
    for i, c in sorted({ic for pairs in plan.values() for ic in pairs}):
        try:
            rel = str(np.asarray(ims[i]["ims"]).reshape(-1)[c])
        except (KeyError, IndexError, TypeError):
            raise UserError(f"{annots_path}: ims[{i}] has no image for camera {c}") from None
        image = root / rel
        if not image.is_file():
            raise UserError(f"frame {i} has no image: {image} does not exist")
        masks = tuple(d / Path(rel).with_suffix(".png") for d in mask_dirs)
        masks = tuple(m for m in masks if m.is_file())
        if not masks:
            raise UserError(f"frame {i} has no mask: none of "
                            f"{', '.join(str(d / Path(rel).with_suffix('.png')) for d in mask_dirs)} exists")
        paths[i, c] = (image, masks)
    return paths


def _converted_params(params_dir: Path, offset: int, used: list[int], body) -> tuple[np.ndarray, dict]:
    """Load the ``used`` frames' ZJU parameters and convert them to SMPL's; returns (shapes [F,10] as
    stored, ``zju_to_smpl_params``'s dict), both in ``used`` order."""
    raw = {i: _load_params(params_dir / f"{i + offset}.npy") for i in used}
    Rh = np.stack([raw[i]["Rh"] for i in used])
    Th = np.stack([raw[i]["Th"] for i in used])
    poses = np.stack([raw[i]["poses"] for i in used])
    shapes = np.stack([raw[i]["shapes"] for i in used])
    J0 = rest_pelvis_provider(body)(shapes.astype(np.float32))
    J0 = np.asarray(J0, np.float64)
    if J0.shape != (len(used), 3):
        raise UserError(f"the rest-pelvis provider returned {list(J0.shape)}, expected [{len(used)},3]")
    return shapes, zju_to_smpl_params(Rh, Th, poses, J0)


def _cameras(cams: dict, plan: dict[str, list], width: int, height: int) -> tuple[dict, dict]:
    """Cameras of the planned views; returns ({camera index: Camera}, {id(Camera): (K, distortion)})."""
    cameras, distortion = {}, {}
    for c in sorted({c for pairs in plan.values() for _, c in pairs}):
        K = np.asarray(cams["K"][c], np.float64)
        viewmat = np.eye(4)
        viewmat[:3, :3] = np.asarray(cams["R"][c], np.float64)
        viewmat[:3, 3] = np.asarray(cams["T"][c], np.float64).reshape(3) / 1000.0  # annots store millimetres
        cameras[c] = Camera(K, viewmat, width, height)
        distortion[id(cameras[c])] = (K, np.asarray(cams["D"][c], np.float64).reshape(-1))
    return cameras, distortion


def _image_size(path: Path) -> tuple[int, int]:
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.size
    except Exception as exc:
        raise UserError(f"cannot read image {path}: {exc}") from None


__all__ = ["open_zju", "zju_to_smpl_params", "rest_pelvis_provider", "undistort_maps", "SPLITS"]
